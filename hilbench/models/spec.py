"""Model specs: parsing, validation of every option, and the memory a fit of the spec needs.

A spec is a base model and effects joined by ``+`` (DESIGN.md): ``pi``, ``pmpi+dynamics``,
``pi(n=16)+creep(n=1)``. Every option a user types is checked against the component's
:class:`Option` (type, range, unit, choices) before anything is built: ``pi(n=2.5)``, ``pi(n=abc)``,
``delay(seconds=-1)`` are refused with the spec, the option, what was expected and a hint.

Sizes are bounded by memory, not by a fixed maximum: :func:`fit_memory` estimates the bytes a fit
of the spec on a given number of samples needs (the regressor matrix and its copies, the normal
equations, the Jacobian of the shape search), and :func:`check_fit_memory` refuses a fit whose
estimate exceeds the limit (``--memory-limit``/``HILBENCH_MEMORY_LIMIT``, default half the
machine's memory) before anything is allocated, with the estimate and the limit in the message.
"""

from __future__ import annotations

import difflib
import os
import re
from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

from hilbench.errors import UserError
from hilbench.models.options import Option
from hilbench.schema import parse_scalar

if TYPE_CHECKING:  # the components are imported in functions: they declare their options with Option
    from hilbench.models.components import Component


class SpecError(UserError):
    """A model spec that cannot be built: says what is available."""


SPEC_HINT = "a spec is BASE or BASE(key=value,...)+EFFECT+..., e.g. 'pi(n=16)+creep'; see `hilbench fit --help`"


def _suggest(word: str, options: Sequence[str]) -> str:
    close = difflib.get_close_matches(word, list(options), n=1, cutoff=0.6)
    return f"did you mean {close[0]!r}?" if close else ""


_PART = re.compile(r"^\s*([A-Za-z_][A-Za-z0-9_\-]*)\s*(?:\((.*)\))?\s*$")
MAX_SPEC_LENGTH = 2000


def split_spec(spec: str) -> list[tuple[str, dict[str, Any]]]:
    """``"pi(n=16)+creep"`` -> ``[("pi", {"n": 16}), ("creep", {})]`` (values not yet checked)."""
    from hilbench.models.bases import BASES
    from hilbench.models.effect_components import EFFECTS

    if not isinstance(spec, str) or not spec.strip():
        raise SpecError("the model spec is empty", where="--model", hint=SPEC_HINT)
    if len(spec) > MAX_SPEC_LENGTH:
        raise SpecError(f"the model spec is {len(spec)} characters long, more than {MAX_SPEC_LENGTH}",
                        where="--model", hint=SPEC_HINT)
    parts: list[str] = []
    depth, current = 0, ""
    for ch in spec:
        if ch == "(":
            depth += 1
        elif ch == ")":
            depth -= 1
            if depth < 0:
                raise SpecError(f"unbalanced ')' in spec {spec!r}", where="--model", hint=SPEC_HINT)
        if ch == "+" and depth == 0:
            parts.append(current)
            current = ""
        else:
            current += ch
    if depth != 0:
        raise SpecError(f"unbalanced '(' in spec {spec!r}", where="--model", hint=SPEC_HINT)
    parts.append(current)
    out = []
    for part in parts:
        match = _PART.match(part)
        if not match or "(" in (match.group(2) or "") or ")" in (match.group(2) or ""):
            raise SpecError(f"cannot read {part.strip()!r} in spec {spec!r}; expected NAME or NAME(key=value,...)",
                            where="--model", hint=SPEC_HINT)
        options: dict[str, Any] = {}
        if match.group(2) is not None:
            for item in (x.strip() for x in match.group(2).split(",")):
                if not item:
                    if match.group(2).strip():
                        raise SpecError(f"empty option in {part.strip()!r} of spec {spec!r}", where="--model",
                                        hint="separate options with single commas: pi(n=16)")
                    continue
                key, eq, value = item.partition("=")
                key = key.strip()
                if not eq or not key or not value.strip():
                    raise SpecError(f"option {item!r} in spec {spec!r}: expected key=value", where="--model",
                                    hint="e.g. pi(n=16), delay(seconds=0.0002)")
                if key in options:
                    raise SpecError(f"option {key!r} given twice in spec {spec!r}", where="--model",
                                    hint="give each option once")
                options[key] = parse_scalar(value)
        name = match.group(1)
        out.append((name.lower() if name.lower() in {**BASES, **EFFECTS} else name, options))
    return out


def available_names() -> str:
    from hilbench.models.bases import BASES
    from hilbench.models.effect_components import EFFECTS

    return (f"bases: {', '.join(BASES)}; effects: {', '.join(EFFECTS)}; "
            "or the name of an auxiliary channel of the recording (e.g. temperature, load)")


def as_option(entry: Any) -> Option:
    """An options_schema entry as an :class:`Option` (a bare ``int``, ``float`` or ``str`` is accepted)."""
    if isinstance(entry, Option):
        return entry
    if entry is int:
        return Option("int")
    if entry is float:
        return Option("number")
    return Option("text")


def check_options(name: str, schema: dict[str, Any], options: dict[str, Any], spec: str) -> dict[str, Any]:
    """Options typed and range-checked against ``schema``; raises :class:`SpecError` naming the value."""
    out: dict[str, Any] = {}
    for key, value in options.items():
        if key not in schema:
            allowed = ", ".join(schema) or "none"
            suggestion = _suggest(key, list(schema))
            raise SpecError(f"{name}: unknown option {key!r} in spec {spec!r}; options: {allowed}", where="--model",
                            hint=suggestion or (f"{name} takes no options" if not schema else
                                                f"e.g. {name}({next(iter(schema))}=...)"))
        option = as_option(schema[key])
        try:
            out[key] = option.check(value)
        except ValueError as exc:
            unit = f" ({option.unit})" if option.unit else ""
            bounded = option.kind == "int" and option.minimum is not None and option.maximum is not None
            rule = f"; {key} must be {option.minimum:g} to {option.maximum:g}" if bounded else ""
            raise SpecError(f"{name}({key}={value}): expected {exc}, got {value!r}{rule} in spec {spec!r}",
                            where="--model", hint=f"{key}{unit}: {option.doc}" if option.doc else None) from None
    return out


def build_components(spec: str, channels: list[str] | None = None) -> tuple[Component, list[Component]]:
    """Base and effects of a spec, validated; aux-channel effects need the channel in ``channels``."""
    from hilbench.models.bases import BASES
    from hilbench.models.effect_components import EFFECT_ORDER, EFFECTS, AuxChannel

    parts = split_spec(spec)
    base_name, base_options = parts[0]
    if base_name not in BASES:
        hint = " (an effect cannot come first)" if base_name in EFFECTS else ""
        raise SpecError(f"unknown base model {base_name!r}{hint} in spec {spec!r}; {available_names()}",
                        where="--model", hint=_suggest(base_name.lower(), list(BASES)) or SPEC_HINT)
    base = BASES[base_name](check_options(base_name, BASES[base_name].options_schema, base_options, spec))
    effects: list[Component] = []
    seen = {base_name}
    for name, options in parts[1:]:
        if name in seen:
            raise SpecError(f"{name!r} appears twice in spec {spec!r}", where="--model", hint="name each effect once")
        seen.add(name)
        if name in BASES:
            raise SpecError(f"{name!r} is a base model; a spec has one base, then effects: {available_names()}",
                            where="--model", hint=SPEC_HINT)
        if name in EFFECTS:
            effect = EFFECTS[name](check_options(name, EFFECTS[name].options_schema, options, spec))
        elif name == "hysteresis":
            raise SpecError(f"'hysteresis' in spec {spec!r} is added by choosing a hysteretic base (pi, pmpi, ...) "
                            "instead of linear",
                            where="--model", hint="e.g. pi+creep instead of linear+hysteresis+creep")
        else:
            if channels is not None and name not in channels:
                aux = [c for c in channels if c not in ("time", "input", "output")]
                raise SpecError(
                    f"{name!r} is neither a model nor an effect, and the recording has no channel {name!r}; "
                    f"{available_names()}; channels here: {', '.join(aux) or 'none'}",
                    where="--model", hint=_suggest(name.lower(), [*EFFECTS, *aux]) or SPEC_HINT,
                )
            effect = AuxChannel(name, check_options(name, {}, options, spec))
        effects.append(effect)
    effects.sort(key=lambda e: EFFECT_ORDER.index(e.name if e.name in EFFECTS else "<aux>"))
    for e in effects:
        e.check_spec(base, effects, spec)
    return base, effects


# -- size and memory ------------------------------------------------------------------------------


def _opt(component: Component, key: str, default: Any = None) -> Any:
    value = component.options.get(key)
    if value is None:
        entry = component.options_schema.get(key)
        value = entry.default if isinstance(entry, Option) and entry.default is not None else default
    return value


def regressor_size(base: Component, effects: list[Component]) -> tuple[int, int]:
    """(regressor columns, searched shape parameters) of a spec, from its options alone.

    Mirrors the ``columns()`` of :mod:`hilbench.models.bases` and :mod:`hilbench.models.effect_components`: effects that modulate the
    hysteresis (saturation's output form, creep's output form, rate-dependence, aux channels) add a
    copy of every hysteresis column so far.
    """
    name = base.name
    if any(e.name == "restoring-force" for e in effects):
        return 0, 6  # one state equation: its physical parameters searched, no columns
    if name == "linear":
        cols, hyst, shape = 2, 1, 0
    elif name in ("pi", "pi1", "mpi", "pmpi", "pd"):
        n = int(_opt(base, "n"))
        extra = 2 if name in ("mpi", "pmpi") else (int(_opt(base, "n_dead_zone")) if name == "pd" else 0)
        cols, hyst, shape = 1 + n + extra, n + extra, (n - 1 if name == "pmpi" else 0)
    elif name == "fpmpi":
        n = int(_opt(base, "n"))
        cols, hyst, shape = 1 + n, n, int(_opt(base, "terms")) - 1
    elif name == "duhem-d":
        n = int(_opt(base, "n"))
        cols, hyst, shape = 3 + 2 * n, 2 + 2 * n, 3
    elif name == "bouc-wen":
        cols, hyst, shape = 3, 2, 2
    else:  # duhem-g, duhem-m
        cols, hyst, shape = 3, 2, 3
    for e in effects:
        kind = "<aux>" if hasattr(e, "channel") else e.name
        if kind == "asymmetry":
            k = int(_opt(e, "order")) - 1
            cols, hyst = cols + k, hyst + k
        elif kind == "saturation" and _opt(e, "form") == "hammerstein":
            shape += 2  # a knee on the drive: no columns of its own
        elif kind == "saturation":
            k = 1 if _opt(e, "form") == "wiener" else 3 + (hyst if _opt(e, "form") in ("output", "knee") else 0)
            cols, hyst, shape = cols + k, hyst + k, shape + (2 if _opt(e, "form") in ("knee", "wiener") else 1)
        elif kind == "creep" and _opt(e, "form") == "bank":
            from hilbench.models.effect_components import CREEP_BANK_MOST

            cols += CREEP_BANK_MOST  # a fixed bank: its time constants are not searched
        elif kind == "creep":
            n = int(_opt(e, "n"))
            cols, shape = cols + n + (n * hyst if _opt(e, "form") == "output" else 0), shape + n
        elif kind == "rate-dependence":
            order = int(_opt(e, "order"))
            # the larger of the two forms (form=auto chooses on the data)
            cols, shape = cols + max(1 + hyst, order + order * (hyst + 1)), shape + 1
        elif kind == "<aux>":
            cols += 1 + hyst
        elif kind == "dynamics":
            k = _opt(e, "kind")
            shape += 1 if k == "first-order" else (2 * int(_opt(e, "pairs")) + int(_opt(e, "zeros"))
                                                   if k == "discrete" else 2)
        elif kind == "delay":
            shape += 1
    return cols, shape


#: rows of the shape search at most (hilbench.identify.separable: max_search_rows)
SEARCH_ROWS = 50_000


def fit_memory(base: Component, effects: list[Component], n_samples: int, n_train: int) -> int:
    """Bytes a fit needs at its peak, estimated from how :mod:`hilbench.identify.separable` and
    :class:`hilbench.models.Model` build the regressor (float64, 8 bytes a number):

    - the static column blocks of every run, kept for the search: n_samples x p;
    - their ``hstack`` per run, and the dynamics filter's output when there is one: 1-2 copies;
    - the training rows gathered from it and stacked over runs: 2 x n_train x p;
    - the normal equations G = A^T A, its scaled copy and its Cholesky factor: 3 x p x p;
    - the shape search's finite-difference Jacobian (scipy least_squares, J and two working copies):
      3 x min(n_train, 50000) x the searched shape parameters.
    """
    p, n_shape = regressor_size(base, effects)
    dynamics = any(e.name == "dynamics" for e in effects)
    design = 8 * p * ((3 if dynamics else 2) * n_samples + 2 * n_train)
    normal = 8 * 3 * p * p
    jacobian = 8 * 3 * min(n_train, SEARCH_ROWS) * n_shape
    return int(design + normal + jacobian)


_SIZE = re.compile(r"^\s*([0-9]*\.?[0-9]+(?:[eE][+-]?[0-9]+)?)\s*([KMGT]i?B?|B)?\s*$", re.IGNORECASE)


def parse_size(text: str, *, where: str = "HILBENCH_MEMORY_LIMIT") -> int:
    """``"4GB"``, ``"512MiB"``, ``"2e9"`` -> bytes (K, M, G, T as powers of 1024)."""
    m = _SIZE.match(str(text))
    if not m:
        raise UserError(f"expected a size like 4GB or 512MB, got {text!r}", where=where,
                        hint="units: B, KB, MB, GB, TB (powers of 1024)")
    suffix = (m.group(2) or "").upper().replace("I", "").rstrip("B")  # "", K, M, G or T
    value = float(m.group(1)) * (1024 ** "_KMGT".index(suffix) if suffix else 1)
    if not value > 0:
        raise UserError(f"expected a size > 0, got {text!r}", where=where)
    return int(value)


def machine_memory() -> int | None:
    try:
        return int(os.sysconf("SC_PAGE_SIZE")) * int(os.sysconf("SC_PHYS_PAGES"))
    except (ValueError, OSError, AttributeError):
        return None


#: the default limit: this fraction of the machine's memory
DEFAULT_MEMORY_FRACTION = 0.5


_limit_override: int | None = None


def set_memory_limit(text: str | None) -> None:
    """The limit ``hilbench --memory-limit SIZE`` gives for this invocation (None: the default)."""
    global _limit_override
    _limit_override = None if text is None else parse_size(text, where="--memory-limit")


def memory_limit() -> int:
    """The limit in bytes: ``--memory-limit``, else HILBENCH_MEMORY_LIMIT, else half the machine's memory."""
    if _limit_override is not None:
        return _limit_override
    text = os.environ.get("HILBENCH_MEMORY_LIMIT")
    if text:
        return parse_size(text)
    total = machine_memory()
    return int(DEFAULT_MEMORY_FRACTION * total) if total else 4 * 1024**3


def format_bytes(n: float) -> str:
    for unit in ("B", "KB", "MB", "GB", "TB", "PB"):
        if n < 1024 or unit == "PB":
            return f"{n:.3g} {unit}" if unit != "B" else f"{int(n)} B"
        n /= 1024
    return f"{n:.3g} PB"  # pragma: no cover


def check_fit_memory(base: Component, effects: list[Component], n_samples: int, n_train: int, spec: str) -> int:
    """Refuse a fit whose estimated memory exceeds the limit; returns the estimate in bytes."""
    need = fit_memory(base, effects, n_samples, n_train)
    limit = memory_limit()
    if need > limit:
        p, n_shape = regressor_size(base, effects)
        raise SpecError(
            f"spec {spec!r} would need about {format_bytes(need)} of memory to fit ({p} regressor columns, "
            f"{n_shape} shape parameters, {n_samples} samples), more than the limit of {format_bytes(limit)}",
            where="--model",
            hint="use fewer operators (e.g. n=16) or fewer samples, or raise the limit with "
            "`hilbench --memory-limit SIZE` or HILBENCH_MEMORY_LIMIT",
        )
    return need
