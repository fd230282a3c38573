"""Text summaries of results for people (the --json documents are for scripts)."""

from __future__ import annotations

from typing import Any


def fit_report_lines(result: Any) -> list[str]:
    """Human summary of a :class:`hilbench.identify.fitting.FitResult`: spec, parameters, metric table, time."""
    from hilbench.identify.metrics import METRIC_KEYS, metric_unit

    model_dict = result.model.to_dict()
    how = "fitted" if result.refitted else f"loaded from {result.loaded_from}, not refitted"
    lines = [f"model: {result.spec} ({how})", f"split: {result.split}"]
    shape = model_dict["parameters"]["shape"]
    if shape:
        lines.append("shape parameters:")
        for p in shape:
            unit = f" {p['unit']}" if p["unit"] else ""
            lines.append(f"  {p['component']:>16s}  {p['name']:<22s} {p['value']:12.6g}{unit}")
    else:
        lines.append("shape parameters: none (weights only)")
    weights = model_dict["parameters"]["weights"]
    y_unit = result.output_unit
    if len(weights) <= 16:
        lines.append(f"weights [{y_unit}]: " + ", ".join(f"{w['name']}={w['value']:.4g}" for w in weights))
    else:
        lines.append(f"weights: {len(weights)} (see -o FIT.json or --json)")
    # a saved model scored on whole runs: one figure (nothing trained); else training and validation
    roles = ("validation",) if not result.refitted and result.metrics["train"]["n"] == 0 else ("train", "validation")
    names = {"train": "train", "validation": "scored" if roles == ("validation",) else "validation"}
    lines.append(f"{'metric':<22s}" + "".join(f"{names[r]:>14s}" for r in roles))
    for key in METRIC_KEYS:
        label = f"{key} [{metric_unit(key, y_unit)}]"
        cells = [result.metrics[role][key] for role in roles]
        lines.append(f"{label:<22s}" + "".join(f"{c:>14.5g}" if c == c else f"{'-':>14s}" for c in cells))
    lines.append(f"{'samples':<22s}" + "".join(f"{result.metrics[r]['n']:>14d}" for r in roles))
    lines.append("runs:")
    for r in result.runs:
        rmse = "  ".join(f"{names.get(role, role)} rmse {m['rmse']:.4g}" for role, m in r.metrics.items() if m)
        role = names.get(r.role, r.role) if roles == ("validation",) else r.role
        lines.append(f"  {r.key:<36s} {role:<17s} {rmse}")
    info = result.fit_info()
    if result.refitted:
        n_eval = info["evaluations"]
        lines.append(f"fit: {info['seconds']:.2f} s, {n_eval} evaluation{'' if n_eval == 1 else 's'} of the weights")
    elif info.get("seconds") is not None:
        lines.append(f"fit: loaded; the original fit took {info['seconds']:.2f} s")
    return lines


def range_text(value: Any) -> str:
    """A where-range for people: numbers to 4 significant digits, a time window as ``run t0-t1 s``."""
    if isinstance(value, list):
        if len(value) == 3 and isinstance(value[0], str):
            return f"{value[0]} {value[1]:.4g}-{value[2]:.4g} s"
        return "[" + ", ".join(f"{v:.4g}" if isinstance(v, float) else str(v) for v in value) + "]"
    return str(value)


def failed_text(candidate: dict[str, Any]) -> str:
    """What a candidate's line adds about its failed checks: the first one's sentence when the
    explanation does not end with it already, and the others by name with measured vs required."""
    failed = (candidate.get("evidence") or {}).get("failed_checks") or []
    if candidate.get("significant") or not failed:
        return ""
    first = failed[0]
    out = "" if candidate["explanation"].endswith(first["text"]) else f"; not significant: {first['text']}"
    if len(failed) > 1:
        out += " (also failed: " + ", ".join(f"{f['check']} {_measured(f['measured'])} vs {f['required']}"
                                             for f in failed[1:]) + ")"
    return out


def _measured(value: Any) -> str:
    if isinstance(value, dict):  # several figures: each with its name (training_gain=0.42, ...)
        return ", ".join(f"{k}={_measured(v)}" for k, v in value.items())
    return f"{value:.3g}" if isinstance(value, (int, float)) else str(value)


#: the longest phrase of a candidate's line in the compact output (characters)
PHRASE_CHARS = 110


def _phrase(text: str, limit: int = PHRASE_CHARS, first_clause: bool = True) -> str:
    """The first clause of a sentence (up to its first ';' or ': '), cut at a word within ``limit``."""
    for stop in ("; ", ": ") if first_clause else ():
        cut = text.find(stop)
        if cut > 20:
            text = text[:cut]
    text = " ".join(text.split())
    if len(text) <= limit:
        return text
    return text[:limit].rsplit(" ", 1)[0] + " ..."


def diagnosis_summary_lines(d: dict[str, Any]) -> list[str]:
    """The diagnosis in one screen: the model's error, where it lies (top three), the verdict, and one
    line per candidate: found or refused, its validation gain, one phrase of why (for a refused one the
    check that failed, measured against required). ``--verbose`` prints :func:`diagnosis_lines`."""
    val, trn = d["metrics"]["validation"], d["metrics"]["train"]
    lines = [f"model: {d['spec']}   validation rmse {val['rmse']:.4g} (erms {val['erms_pct']:.3g} % of range), "
             f"training {trn['rmse']:.4g}"]
    for note in d.get("notes", []):
        lines.append(f"note: {_phrase(note, 160)}")
    where = sorted(d["where"], key=lambda e: -e["share"])[:3]
    if where:
        lines.append("error lies most in: " + "; ".join(
            f"{e['kind']} {range_text(e['range'])} ({100 * e['share']:.0f} % of it in "
            f"{100 * e.get('fraction_of_rows', float('nan')):.0f} % of rows)" for e in where))
    found = [e for e in d["effects"] if e["significant"]]
    if found:
        best = found[0]
        ev = best.get("evidence") or {}
        # another base or a structure replaces the model (its evidence names the replacement): no --add
        how = (f"--model '{ev['spec']}' or --auto switches to it" if "replacement" in ev and "spec" in ev
               else f"--add {best['effect'].split('+')[0]} or --auto adds it")
        lines.append(f"verdict: {best['effect']} is missing (validation rmse {-100 * best['expected_gain']:+.1f} % "
                     f"with it); {how}")
    else:
        lines.append("verdict: no missing effect is significant" + (" (some could not be tested)" if d["untestable"] else ""))
    if d["effects"]:
        width = max(16, *(len(e["effect"]) for e in d["effects"]))
        lines.append(f"  {'candidate':<{width}s} {'verdict':<8s} {'gain':>7s}  why")
        for e in d["effects"]:
            failed = (e.get("evidence") or {}).get("failed_checks") or []
            if e["significant"] or not failed:
                why = _phrase(e["explanation"])
            else:
                why = _phrase(failed[0]["text"], 2 * PHRASE_CHARS, first_clause=False)  # measured vs required
            verdict = "found" if e["significant"] else "refused"
            lines.append(f"  {e['effect']:<{width}s} {verdict:<8s} {100 * e['expected_gain']:6.1f}%  {why}")
    else:
        lines.append("  no effect testable")
    for u in d["untestable"]:
        lines.append(f"  {u['effect']:<16s} untestable: {_phrase(u['reason'])}")
    if d.get("steps"):
        lines.append("steps: " + " -> ".join(f"{s['spec']} ({s['validation']['rmse']:.4g})" for s in d["steps"]))
    return lines


def diagnosis_lines(d: dict[str, Any]) -> list[str]:
    """The diagnosis check by check (``diagnose --verbose``)."""
    val = d["metrics"]["validation"]
    trn = d["metrics"]["train"]
    lines = [f"model: {d['spec']}   rmse train {trn['rmse']:.4g}, validation {val['rmse']:.4g} "
             f"(erms {val['erms_pct']:.3g} % of range)"]
    for note in d.get("notes", []):
        lines.append(f"note: {note}")
    lines.append("where the validation error is (share of the squared error):")
    for entry in sorted(d["where"], key=lambda e: -e["share"])[:8]:
        lines.append(f"  {entry['kind']:<18s} {range_text(entry['range']):<42s} {100 * entry['share']:6.1f} %"
                     f"  (of {100 * entry.get('fraction_of_rows', float('nan')):.3g} % of rows)")
    lines.append("effects (best first):")
    for e in d["effects"]:
        mark = "significant" if e["significant"] else "not significant"
        lines.append(f"  {e['effect']:<16s} {mark:<16s} expected gain {100 * e['expected_gain']:6.1f} %  "
                     f"{e['explanation']}{failed_text(e)}")
    if not d["effects"]:
        lines.append("  none testable")
    for u in d["untestable"]:
        lines.append(f"  {u['effect']:<16s} untestable: {u['reason']}")
    if d.get("steps"):
        lines.append("step  spec                                   added             validation rmse")
        for k, s in enumerate(d["steps"]):
            line = f"{k:>4d}  {s['spec']:<38s} {str(s['added'] or '-'):<17s} {s['validation']['rmse']:.4g}"
            if s.get("within_reach"):
                reach = s["within_reach"]
                before, after = reach["validation_rmse"]
                line += (f"  (judged within training's input reach, {reach['left_out']} of {reach['validation_rows']} "
                         f"rows left out: {before:.4g} -> {after:.4g})")
            lines.append(line)
    return lines
