"""The schema engine the task and material files are checked with (docs/formats.md): one Spec per
key, sections of them, unit suffixes converted to SI, and the YAML reader.

Every problem becomes one TaskError naming the file, the dotted key path (`camera.lens.f_number_range`,
`requirements.gray_band[1]`), what was found and what was expected; a schema reads like its file.
"""

from __future__ import annotations

import difflib
import re
import reprlib
from collections.abc import Callable, Iterator, Mapping
from os import PathLike
from pathlib import Path
from typing import Any, TypedDict

import numpy as np
import yaml

from cell.core import geometry
from cell.core.errors import TaskError
from cell.core.inputs import read_text

# a unit suffix's conversion of a number (or an array of them) to SI
ToSI = Callable[[Any], Any]
# unit suffix -> (quantity, conversion to SI); division keeps 230.43 mW == 0.23043 W exact
UNITS: dict[str, tuple[str, ToSI]] = {
    "m": ("length", lambda v: v), "mm": ("length", lambda v: v / 1e3), "um": ("length", lambda v: v / 1e6),
    "s": ("time", lambda v: v), "ms": ("time", lambda v: v / 1e3),
    "deg": ("angle", np.radians), "rad": ("angle", lambda v: v),
    "w": ("power", lambda v: v), "mw": ("power", lambda v: v / 1e3),
}
SI_SUFFIX = {"length": "m", "time": "s", "angle": "rad", "power": "w"}
REQUIRED = object()


class Invalid(Exception):
    """A bad value, before the section parser adds the file and the key path."""

    def __init__(self, found: Any, expected: str, index: int | None = None) -> None:
        super().__init__(expected)
        self.found, self.expected, self.index = found, expected, index


def _plain(value):
    """numpy scalars and arrays, and lists of them, as the plain Python values a file holds."""
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value[:_SHORT.maxlist + 1]]
    return value


_SHORT = reprlib.Repr()
_SHORT.maxlevel, _SHORT.maxlist, _SHORT.maxdict, _SHORT.maxstring, _SHORT.maxother = 3, 10, 4, 60, 60


def show(value: Any) -> str:
    """A value as the file wrote it, on one short line: `0.6`, `[0.6, 0.6, 0.1]`, never numpy's
    reprs such as `np.float64(0.6)`, which no user wrote. Long or deep values are cut before
    they are written out (an alias bomb in YAML holds billions of elements)."""
    value = _plain(value)
    if isinstance(value, dict):
        return "a mapping"
    return clip("null" if value is None else _SHORT.repr(value))


def clip(text: str, length: int = 80) -> str:
    """text on at most `length` characters, cut with '...'."""
    return text if len(text) <= length else text[:length - 3] + "..."


def _number(raw, expected, index=None, finite=True):
    """raw as a float; bools and text are not numbers, NaN and inf are rejected if finite."""
    if isinstance(raw, bool) or not isinstance(raw, (int, float)):
        raise Invalid(raw, expected, index)
    try:
        value = float(raw)
    except OverflowError:                                        # an integer such as 10**400
        value = float("inf") if raw > 0 else float("-inf")
    if finite and not np.isfinite(value):
        raise Invalid(raw, "a finite number", index)
    return value


def _numbers(raw, length, expected):
    """raw as a float array of exactly `length` numbers, element errors indexed."""
    if not isinstance(raw, list) or len(raw) != length:
        raise Invalid(raw, expected)
    return np.array([_number(x, "a number", i) for i, x in enumerate(raw)])


class Spec:
    """One key's rule: `convert` checks the raw YAML value and returns it in SI units."""

    expected = "a value"
    default = REQUIRED
    # (file, path, raw, SI value) -> None or TaskError: the range a cell can have (cell.task.plausible)
    plausible: Callable[[str | PathLike[str], str, Any, Any], None] | None = None

    def read(self, file: str | PathLike[str], path: str, raw: Any, to_si: ToSI) -> Any:
        try:
            value = self.convert(raw, to_si)
        except Invalid as bad:
            key = path if bad.index is None else f"{path}[{bad.index}]"
            raise TaskError(file, key, show(bad.found), bad.expected) from None
        if self.plausible is not None:
            self.plausible(file, path, raw, value)
        return value

    def convert(self, raw: Any, to_si: ToSI) -> Any:
        """raw checked and in SI units; an Invalid says what is wrong (each kind of key its own)."""
        raise NotImplementedError

    def absent(self, file: str | PathLike[str], path: str) -> Any:
        if self.default is REQUIRED:
            raise TaskError(file, path, "nothing", f"{self.expected} (required key)")
        return self.default


class Text(Spec):
    expected = "a non-empty text"

    def __init__(self, default: Any = REQUIRED) -> None:
        self.default = default

    def convert(self, raw: Any, to_si: ToSI) -> str:
        if not isinstance(raw, str) or not raw.strip():
            raise Invalid(raw, self.expected)
        return raw.strip()


class Choice(Spec):
    def __init__(self, *options: str, default: Any = REQUIRED) -> None:
        self.options, self.default = options, default
        self.expected = "one of " + " | ".join(options)

    def convert(self, raw: Any, to_si: ToSI) -> str:
        if raw not in self.options:
            raise Invalid(raw, self.expected)
        return raw


class Number(Spec):
    """A finite number whose SI value passes `ok`."""

    def __init__(self, ok: Callable[[float], bool], expected: str, default: Any = REQUIRED) -> None:
        self.ok, self.expected, self.default = ok, expected, default

    def convert(self, raw: Any, to_si: ToSI) -> float:
        value = to_si(_number(raw, self.expected))
        if not self.ok(value):
            raise Invalid(raw, self.expected)
        return float(value)


class Integer(Spec):
    def __init__(self, low: int, high: int | None = None, default: Any = REQUIRED) -> None:
        self.low, self.high, self.default = low, high, default
        self.expected = f"an integer in {low}..{high}" if high else f"an integer >= {low}"

    def convert(self, raw: Any, to_si: ToSI) -> int:
        is_int = isinstance(raw, int) and not isinstance(raw, bool)
        if not is_int or raw < self.low or (self.high and raw > self.high):
            raise Invalid(raw, self.expected)
        return raw


class Vector(Spec):
    """A 3-vector; `direction` rejects the zero vector and normalizes. A default (SI) is given as
    a tuple, and each task gets its own array of it."""

    def __init__(self, direction: bool = False, default: Any = REQUIRED) -> None:
        self.direction, self.default = direction, default
        self.expected = "a non-zero 3-vector [x, y, z]" if direction else "a 3-vector [x, y, z]"

    def absent(self, file: str | PathLike[str], path: str) -> np.ndarray | None:
        default = super().absent(file, path)
        return None if default is None else np.array(default, float)

    def convert(self, raw: Any, to_si: ToSI) -> np.ndarray:
        v = to_si(_numbers(raw, 3, self.expected))
        if self.direction:
            if not np.linalg.norm(v) > 0:
                raise Invalid(raw, self.expected)
            v = geometry.unit(v)
        return v


class Pair(Spec):
    """A range [low, high] of numbers passing `ok` (SI); low < high if strict, else low <= high;
    not `ascending`: two numbers in either order (a width and a height)."""

    def __init__(self, ok: Callable[[float], bool], what: str, strict: bool = False,
                 default: Any = REQUIRED, ascending: bool = True) -> None:
        self.ok, self.strict, self.default, self.ascending = ok, strict, default, ascending
        self.expected = f"an ascending pair of {what}" if ascending else f"a pair of {what}"

    def convert(self, raw: Any, to_si: ToSI) -> tuple[float, float]:
        low, high = to_si(_numbers(raw, 2, self.expected))
        ordered = not self.ascending or (low < high if self.strict else low <= high)
        if not (self.ok(low) and self.ok(high)) or not ordered:
            raise Invalid(raw, self.expected)
        return float(low), float(high)


class Band(Spec):
    """A gray band: an ascending pair of gray levels (low < high), or the text `any` (kept as "any"):
    only a declared defect's contrast matters (the loader then takes the sensor's range,
    cell.task.loader.any_band)."""

    def __init__(self, default: Any = REQUIRED) -> None:
        self.pair = Pair(lambda v: True, "gray levels", strict=True)
        self.default = default
        self.expected = f"{self.pair.expected}, or any"

    def convert(self, raw: Any, to_si: ToSI) -> tuple[float, float] | str:
        if raw == "any":
            return "any"
        try:
            return self.pair.convert(raw, to_si)
        except Invalid as bad:
            raise Invalid(bad.found, self.expected, bad.index) from None


class Flag(Spec):
    """true or false (YAML's booleans; 0 and 1 are numbers, not flags)."""

    expected = "true or false"

    def __init__(self, default: Any = REQUIRED) -> None:
        self.default = default

    def convert(self, raw: Any, to_si: ToSI) -> bool:
        if not isinstance(raw, bool):
            raise Invalid(raw, self.expected)
        return raw


class Table(Spec):
    """A table column: one number per row (a material's phase angle, a lamp profile's off-axis
    angle), each passing `ok`."""

    def __init__(self, ok: Callable[[float], bool], expected: str, default: Any = REQUIRED, finite: bool = True,
                 per: str = "phase angle") -> None:
        self.ok, self.element, self.default, self.finite = ok, expected, default, finite
        self.expected = f"a list with one value per {per}, each {expected}"

    def convert(self, raw: Any, to_si: ToSI) -> np.ndarray:
        if not isinstance(raw, list) or not raw:
            raise Invalid(raw, self.expected)
        values = to_si(np.array([_number(x, self.element, i, self.finite) for i, x in enumerate(raw)]))
        for i, v in enumerate(values):
            if not self.ok(v):
                raise Invalid(raw[i], self.element, i)
        return values



class Anything(Spec):
    """Fitter notes kept verbatim (e.g. `unidentifiable`)."""

    default = None

    def convert(self, raw: Any, to_si: ToSI) -> Any:
        return raw


class Section(Spec):
    """A nested mapping of keys; an optional section missing from the file takes its defaults."""

    expected = "a mapping of keys"

    def __init__(self, fields: Mapping[str, Spec], required: bool = True, defaults: bool = True) -> None:
        """required: missing is an error; otherwise a missing section takes the defaults of all
        its keys, or is None when not `defaults` (one of two alternative sections)."""
        self.fields, self.required, self.defaults = fields, required, defaults

    def read(self, file: str | PathLike[str], path: str, raw: Any, to_si: ToSI) -> dict[str, Any]:
        return parse(file, path, raw, self.fields)

    def absent(self, file: str | PathLike[str], path: str) -> dict[str, Any] | None:
        if self.required:
            raise TaskError(file, path, "nothing", f"{self.expected} (required section)")
        return parse(file, path, {}, self.fields) if self.defaults else None


class Sections(Spec):
    """A non-empty list of sections, each checked against `fields`; an error names the entry,
    `features[2].radius_m`. Absent: None (it is an alternative to another key)."""

    expected = "a non-empty list of mappings of keys"
    default = None

    def __init__(self, fields: Mapping[str, Spec]) -> None:
        self.fields = fields

    def read(self, file: str | PathLike[str], path: str, raw: Any, to_si: ToSI) -> list[dict[str, Any]]:
        if not isinstance(raw, list) or not raw:
            raise TaskError(file, path, show(raw), self.expected)
        return [parse(file, f"{path}[{i}]", item, self.fields) for i, item in enumerate(raw)]


def schema_keys(fields: Mapping[str, Spec], path: str = "") -> Iterator[tuple[str, Spec]]:
    """(dotted key, Spec) of every key and section of a schema, depth first; the keys of each
    entry of a list of sections as `features[].center_m` (docs/formats.md's rows)."""
    for key, spec in fields.items():
        dotted = f"{path}.{key}" if path else key
        yield dotted, spec
        if isinstance(spec, Section):
            yield from schema_keys(spec.fields, dotted)
        if isinstance(spec, Sections):
            yield from schema_keys(spec.fields, f"{dotted}[]")


class Rule(TypedDict):
    """A Number's or Table's test of a value and what the message says it expected."""

    ok: Callable[[float], bool]
    expected: str


# common rules: Number(**POSITIVE), Table(**NON_NEGATIVE)
POSITIVE = Rule(ok=lambda v: v > 0, expected="a positive number")
NON_NEGATIVE = Rule(ok=lambda v: v >= 0, expected="a number >= 0")


def _join(path, key):
    return f"{path}.{key}" if path else str(key)


def _unit(key):
    """(base, suffix) of a key whose last `_` part is a unit suffix, else (key, None).
    A rate such as `speed_m_s` (base ending in a unit too) is not a unit variant of `speed_m`."""
    base, _, suffix = key.rpartition("_")
    if not base or suffix not in UNITS or base.rpartition("_")[2] in UNITS:
        return key, None
    return base, suffix


def _schema_key(file, path, written, fields):
    """The schema key a file key stands for (the same quantity in any accepted unit)."""
    if written in fields:
        return written
    dimensioned = {base: key for key in fields for base, suffix in [_unit(key)] if suffix}
    base, _, suffix = written.rpartition("_")
    if base in dimensioned:
        quantity = UNITS[_unit(dimensioned[base])[1]][0]
        if UNITS.get(suffix, ("",))[0] == quantity:
            return dimensioned[base]
        units = ", ".join(s for s, (q, _) in UNITS.items() if q == quantity)
        raise TaskError(file, _join(path, written), f"unit '{suffix}'", f"a {quantity} unit: {units}")
    hint = difflib.get_close_matches(written, list(fields), n=1)
    expected = "one of " + ", ".join(fields) + (f"; did you mean '{hint[0]}'?" if hint else "")
    raise TaskError(file, _join(path, written), "an unknown key", expected)


def parse(file: str | PathLike[str], path: str, data: Any, fields: Mapping[str, Spec]) -> dict[str, Any]:
    """Check a mapping against its fields (an empty value counts as absent); returns
    {key with SI suffix: SI value}."""
    if not isinstance(data, dict):
        raise TaskError(file, path, show(data), "a mapping of keys")
    given: dict[str, str] = {}
    for written in data:
        key = _schema_key(file, path, str(written), fields)
        if key in given:
            raise TaskError(file, _join(path, written), f"{given[key]} and {written} both",
                            "the value in one unit only")
        given[key] = written
    values = {}
    for key, spec in fields.items():
        base, suffix = _unit(key)
        si_key = f"{base}_{SI_SUFFIX[UNITS[suffix][0]]}" if suffix else key
        written = given.get(key)
        if written is not None and data[written] is not None:
            to_si = UNITS[_unit(written)[1]][1] if suffix else (lambda v: v)
            values[si_key] = spec.read(file, _join(path, written), data[written], to_si)
        else:
            values[si_key] = spec.absent(file, _join(path, key))
    return values


MAX_DEPTH = 32          # nesting levels: a task needs 4; deeper is a mistake or an attack
MAX_VALUES = 100_000    # values with every alias expanded: a few lines of aliases can expand to
                        # billions ("billion laughs"); a task has a few hundred


# libyaml's C parser where installed (a name PyYAML defines only then)
_SAFE_LOADER: Any = getattr(yaml, "CSafeLoader", yaml.SafeLoader)


class _YamlLoader(_SAFE_LOADER):
    """The safe loader (libyaml's C parser where installed) reading YAML 1.2 floats (1e-5,
    1.5e16 are numbers) and rejecting duplicate keys."""

    def construct_mapping(self, node: yaml.MappingNode, deep: bool = False) -> dict[Any, Any]:
        seen = set()
        for key_node, _ in node.value:
            if isinstance(key_node, yaml.ScalarNode):
                if key_node.value in seen:
                    raise yaml.constructor.ConstructorError(
                        None, None, f"duplicate key '{key_node.value}'", key_node.start_mark)
                seen.add(key_node.value)
        return super().construct_mapping(node, deep)


_YamlLoader.add_implicit_resolver("tag:yaml.org,2002:float", re.compile(
    r"^[-+]?(?:[0-9][0-9_]*)(?:\.[0-9_]*)?[eE][-+]?[0-9]+$"), list("-+0123456789"))


def _check_structure(path, text):
    """Refuse nesting deeper than MAX_DEPTH and more than MAX_VALUES values with the aliases
    expanded, from the parser's events alone (nothing is built, nothing expanded)."""
    sizes, open_counts = {}, []          # anchor -> values it expands to; one count per open level

    def refuse(event, found, expected):
        raise TaskError(f"{path}:{event.start_mark.line + 1}", "", found, expected)

    for event in yaml.parse(text, Loader=_YamlLoader):
        if isinstance(event, (yaml.SequenceStartEvent, yaml.MappingStartEvent)):
            open_counts.append([event.anchor, 1])
            if len(open_counts) > MAX_DEPTH:
                refuse(event, f"nesting deeper than {MAX_DEPTH} levels", "a task or material file (4 levels)")
            continue
        if isinstance(event, (yaml.SequenceEndEvent, yaml.MappingEndEvent)):
            anchor, n = open_counts.pop()
        elif isinstance(event, yaml.ScalarEvent):
            anchor, n = event.anchor, 1
        elif isinstance(event, yaml.AliasEvent):
            anchor, n = None, sizes.get(event.anchor, 1)
        else:
            continue
        if anchor:
            sizes[anchor] = n
        if open_counts:
            open_counts[-1][1] += n
        if sum(count for _, count in open_counts) > MAX_VALUES:
            refuse(event, f"more than {MAX_VALUES} values with its YAML aliases expanded",
                   "a task or material file (a few hundred values)")


def read_yaml(path: str | PathLike[str]) -> Any:
    """A YAML file's content: a regular file under the size limit (cell.core.inputs), nested at most
    MAX_DEPTH deep with at most MAX_ALIASES aliases; any problem is a TaskError (file:line)."""
    path = Path(path)
    text = read_text(path, "yaml")
    try:
        _check_structure(path, text)
        return yaml.load(text, Loader=_YamlLoader)
    except yaml.constructor.ConstructorError as err:
        mark = err.problem_mark or err.context_mark
        where = f"{path}:{mark.line + 1}" if mark else path
        problem = clip(" ".join(str(err.problem).split()))
        if problem.startswith("duplicate key"):
            raise TaskError(where, "", f"a {problem}", "each key once") from None
        raise TaskError(where, "", f"a value plain YAML cannot hold ({problem})",
                        "mappings, lists, numbers and text (no tags)") from None
    except yaml.YAMLError as err:
        mark = getattr(err, "problem_mark", None)
        where = f"{path}:{mark.line + 1}" if mark else path
        problem = clip(" ".join(str(getattr(err, "problem", None) or err).split()))
        raise TaskError(where, "", f"a YAML syntax error ({problem})", "valid YAML") from None
