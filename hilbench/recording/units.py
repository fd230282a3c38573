"""Text and unit spellings of imported files: how a CSV file's bytes become text, and one
spelling per unit (um, degC, Ohm, s) whatever the file or the tool that wrote it used."""

from __future__ import annotations

import unicodedata

#: Time units a source may use, with their value in s; time is always recorded in s.
TIME_UNITS_S = {"s": 1.0, "sec": 1.0, "ms": 1e-3, "us": 1e-6, "µs": 1e-6, "ns": 1e-9, "min": 60.0, "h": 3600.0}


def decode_text(raw: bytes) -> str:
    """Text of a CSV file in UTF-8 (with or without BOM), UTF-16 (with BOM), Windows-1252 or Latin-1.

    Decoded line by line where the whole file is not UTF-8, so one Latin-1 line (a comment written
    by another tool) does not garble the UTF-8 header; "Âµm"-style double encodings are repaired
    in :func:`normalize_unit`.
    """
    if raw.startswith((b"\xff\xfe", b"\xfe\xff")):
        return raw.decode("utf-16")
    if raw.startswith(b"\xef\xbb\xbf"):
        raw = raw[3:]
    try:
        return raw.decode("utf-8")
    except UnicodeDecodeError:
        pass
    lines = []
    for line in raw.split(b"\n"):
        try:
            lines.append(line.decode("utf-8"))
        except UnicodeDecodeError:
            try:
                lines.append(line.decode("cp1252"))
            except UnicodeDecodeError:
                lines.append(line.decode("latin-1"))
    return "\n".join(lines)


_UNIT_WORDS = {
    "micron": "um", "microns": "um", "micrometer": "um", "micrometers": "um", "micrometre": "um",
    "micrometres": "um", "mum": "um", "degc": "degC", "deg c": "degC", "deg_c": "degC", "celsius": "degC",
    "°c": "degC", "ºc": "degC", "˚c": "degC", "c°": "degC", "ohm": "Ohm", "ohms": "Ohm", "kohm": "kOhm",
    "mohm": "mOhm", "sec": "s", "secs": "s", "second": "s", "seconds": "s", "volt": "V", "volts": "V",
    "amp": "A", "amps": "A", "ampere": "A", "newton": "N", "newtons": "N", "hz": "Hz", "khz": "kHz",
}


def normalize_unit(unit: str) -> str:
    """One spelling per unit: µm, μm, um, micron -> um; °C, deg C -> degC; Ω, ohm -> Ohm; µs -> us.

    Repairs UTF-8 text that was decoded as Latin-1 on the way ("Âµm", "Â°C", "Î©").
    """
    text = unit.strip()
    if any(marker in text for marker in ("Â", "Ã", "Î", "Ï")):
        for codec in ("cp1252", "latin-1"):
            try:
                text = text.encode(codec).decode("utf-8")
                break
            except (UnicodeEncodeError, UnicodeDecodeError):
                continue
    text = unicodedata.normalize("NFKC", text)  # micro sign -> Greek mu, ohm sign -> Greek omega
    word = _UNIT_WORDS.get(text.lower())
    if word is not None:
        return word
    text = text.replace("μ", "u").replace("Ω", "Ohm").replace("°C", "degC").replace("ºC", "degC")
    return text.replace("°", "deg").replace("º", "deg")
