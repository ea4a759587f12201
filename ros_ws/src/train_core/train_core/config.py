"""Strict, friendly YAML validation shared by every file the project reads.

Pure Python (PyYAML only). Every problem becomes a :class:`ConfigError` whose message is one line
naming the file, the key and what is allowed, so command-line tools can print it and exit 2
instead of showing a traceback.
"""

from __future__ import annotations

import difflib
import math
import re
import warnings
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

import yaml


class ConfigError(ValueError):
    """A configuration file or parameter is wrong; the message is one line, ready to print."""


# libyaml's parser where PyYAML was built with it: the same safe constructor and resolver on
# the same events, a tenth of the pure-Python parser's time (a line map: 2 ms instead of 16)
_SAFE_LOADER = getattr(yaml, "CSafeLoader", yaml.SafeLoader)


class _Loader(_SAFE_LOADER):
    """The safe loader, reading numbers as YAML 1.2 does too: ``5e3`` and ``1E-4`` (no dot or
    no exponent sign) are floats, not strings (YAML 1.1's resolver wants ``5.0e+3``), so a
    mass of ``5e3`` is not refused as "expected a number"."""


_Loader.add_implicit_resolver(
    "tag:yaml.org,2002:float",
    re.compile(r"^[-+]?(?:[0-9][0-9_]*)(?:\.[0-9_]*)?[eE][-+]?[0-9]+$"),
    list("-+0123456789"))


def _text(p: Path) -> str:
    """The file's text: UTF-8 (a byte-order mark dropped). Another encoding is refused by name,
    with what to do: a latin-1 or cp1252 file (a station named Zürich from a Windows editor)
    would otherwise fail deep in the parser."""
    raw = p.read_bytes()
    if raw[:2] in (b"\xff\xfe", b"\xfe\xff"):
        raise ConfigError(f"{p}: UTF-16 text (a byte-order mark {raw[:2].hex()}); save it as "
                          f"UTF-8 (e.g. iconv -f utf-16 -t utf-8)")
    try:
        return raw.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        line = raw[:exc.start].count(b"\n") + 1
        raise ConfigError(f"{p}: not UTF-8 text (byte 0x{raw[exc.start]:02x} on line {line}); "
                          f"save it as UTF-8 (e.g. iconv -f cp1252 -t utf-8)") from None


def _check_nodes(p: Path, root) -> None:
    """Refuse what YAML reads without a word but not as written: a mapping that gives one key
    twice (loaders keep the last: a second ``gradients:`` block would drop the first block's
    sections), and a decimal comma in a flow mapping (``{permille: -3,5}`` is ``permille: -3``
    and a key ``5`` with no value)."""
    def walk(node) -> None:
        if isinstance(node, yaml.MappingNode):
            seen: dict = {}
            for i, (k, v) in enumerate(node.value):
                if node.flow_style and i > 0 and isinstance(k, yaml.ScalarNode) and \
                        k.value.isdigit() and isinstance(v, yaml.ScalarNode) and v.value == "" \
                        and re.fullmatch(r"[-+]?[0-9.]+", str(node.value[i - 1][1].value)):
                    prev = node.value[i - 1]
                    raise ConfigError(
                        f"{p}: line {k.start_mark.line + 1}: '{prev[0].value}: "
                        f"{prev[1].value},{k.value}' reads as {prev[1].value} and a key "
                        f"'{k.value}': a decimal comma? write {prev[1].value}.{k.value}")
                if isinstance(k, yaml.ScalarNode):
                    if k.value in seen:
                        raise ConfigError(
                            f"{p}: key '{k.value}' given twice in one mapping (lines "
                            f"{seen[k.value]} and {k.start_mark.line + 1}): YAML would keep "
                            f"the second only; merge them into one")
                    seen[k.value] = k.start_mark.line + 1
                walk(v)
        elif isinstance(node, yaml.SequenceNode):
            for v in node.value:
                walk(v)

    if root is not None:
        walk(root)


def load_yaml(path: str | Path) -> dict:
    """Read a YAML mapping (UTF-8, no key given twice in one mapping, no decimal comma in a
    flow mapping: :func:`_check_nodes`), turning every failure into a one-line
    :class:`ConfigError`."""
    p = Path(path)
    if not p.is_file():
        raise ConfigError(f"{p}: file not found")
    text = _text(p)
    try:
        # one parse: the node tree is checked, then made into Python values
        loader = _Loader(text)
        try:
            root = loader.get_single_node()
            _check_nodes(p, root)
            data = None if root is None else loader.construct_document(root)
        finally:
            loader.dispose()
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f" (line {mark.line + 1})" if mark is not None else ""
        problem = getattr(exc, "problem", None)
        why = f": {problem}" if problem else ""
        lines = text.splitlines()
        if mark is not None and mark.line < len(lines) and "\t" in lines[mark.line]:
            why += " (a tab on that line: YAML indents with spaces, not tabs)"
        raise ConfigError(f"{p}: not valid YAML{where}{why}") from None
    if not isinstance(data, dict):
        raise ConfigError(f"{p}: expected a mapping at the top level, got {type(data).__name__}")
    return data


class ConfigWarning(UserWarning):
    """A configuration file holds something the loader ignores (an unknown top-level key)."""


def show_config_warnings_on_one_line() -> None:
    """From now on a :class:`ConfigWarning` shows as one line on stderr, ``warning: FILE:
    unknown key ...``, not Python's two lines with the source line that emitted it; other
    warnings as before. For command-line tools (idempotent)."""
    import sys

    default = warnings.showwarning
    if getattr(default, "config_one_line", False):
        return

    def show(message, category, filename, lineno, file=None, line=None):
        if issubclass(category, ConfigWarning):
            print(f"warning: {message}", file=file or sys.stderr)
        else:
            default(message, category, filename, lineno, file, line)

    show.config_one_line = True
    warnings.showwarning = show


# The kinds of value a key holds, for telling a typo that would change the model from an extra
# key a producer added: "number", "integer", "string", "boolean", "list", "mapping" or "any".
_KIND_TESTS = {
    "number": lambda v: isinstance(v, (int, float)) and not isinstance(v, bool),
    "integer": lambda v: isinstance(v, int) and not isinstance(v, bool),
    "string": lambda v: isinstance(v, str),
    "boolean": lambda v: isinstance(v, bool),
    "list": lambda v: isinstance(v, (list, tuple)),
    "mapping": lambda v: isinstance(v, Mapping),
    "any": lambda v: True,
}
_KIND_WORDS = {"number": "a number", "integer": "an integer", "string": "a string",
               "boolean": "true or false", "list": "a list", "mapping": "a mapping",
               "any": "a value"}
NEAR_CUTOFF = 0.75  # difflib ratio from which an unknown key is named as a near miss


def near_misses(key: str, known: Iterable[str], n: int = 3) -> list[str]:
    """The known keys that ``key`` may be a misspelling of, closest first."""
    return difflib.get_close_matches(str(key), list(known), n=n, cutoff=NEAR_CUTOFF)


def unknown_key(key, value, known: Mapping[str, str], present: Iterable[str], where: str,
                what: str = "key") -> str | None:
    """The one rule for a key a reader does not know (every file whose format allows extras).

    Returns None when ``key`` is known. Otherwise the key is allowed (a producer may keep more
    than the project reads) and the text of a warning naming its near misses is returned,
    except where the typo would silently change the model: a near miss that is absent
    (``present``: the keys given) and whose kind of value (``known[near]``, see _KIND_TESTS)
    ``value`` has, e.g. ``gradeints:`` holding a list of sections without ``gradients``. That
    is a :class:`ConfigError` naming the key meant."""
    if key in known:
        return None
    close = near_misses(key, known)
    present = set(present)
    for near in close:
        kind = known[near]
        if near not in present and _KIND_TESTS[kind](value):
            raise ConfigError(f"{where}: unknown {what} '{key}': did you mean '{near}'? (it "
                              f"holds {_KIND_WORDS[kind]}, as '{near}' would, and '{near}' is "
                              f"absent: rename it, or the model goes without it)")
    if close:
        hint = "; near: " + ", ".join(
            f"'{c}'" + (" (given)" if c in present else f" (holds {_KIND_WORDS[known[c]]})")
            for c in close)
    else:
        hint = f" (known: {', '.join(known)})"
    return f"{where}: unknown {what} '{key}' is ignored{hint}"


def warn_unknown(message: str, stacklevel: int = 3) -> None:
    """Report an unknown key: a :class:`ConfigWarning`, which Python prints on stderr (the
    tools' log) and tests can catch."""
    warnings.warn(message, ConfigWarning, stacklevel=stacklevel + 1)


def check_top_level(data: Mapping, known: Mapping[str, str], where: str) -> None:
    """Top-level keys of a file whose format allows extra keys (``known``: key -> the kind of
    value it holds, see _KIND_TESTS): each unknown key goes through :func:`unknown_key`, a
    :class:`ConfigWarning` naming its near misses, or a :class:`ConfigError` where it is a
    typo of an absent key holding that key's kind of value."""
    check_keys(data, known, where, stacklevel=4)


def check_keys(data: Mapping, known: Mapping[str, str], where: str, what: str = "key",
               stacklevel: int = 3) -> None:
    """:func:`unknown_key` for every key of ``data`` (the reader of a mapping with extras)."""
    for key, value in data.items():
        msg = unknown_key(key, value, known, data.keys(), where, what)
        if msg is not None:
            warn_unknown(msg, stacklevel=stacklevel)


class Section:
    """A view on one mapping of a YAML file that checks keys and values as they are read.

    ``where`` is the file and the dotted key path, used in every error message. ``allowed``: a
    list of keys (any other is an error) or, for a mapping whose format allows extra keys, a
    mapping key -> kind of value (:func:`check_keys`: an unknown key is a warning, a typo of an
    absent key holding its kind of value an error).
    """

    def __init__(self, data: Any, where: str,
                 allowed: Iterable[str] | Mapping[str, str] | None = None):
        if not isinstance(data, Mapping):
            raise ConfigError(f"{where}: expected a mapping, got {type(data).__name__}")
        self.data = dict(data)
        self.where = where
        if isinstance(allowed, Mapping):
            check_keys(self.data, allowed, where, stacklevel=5)
        elif allowed is not None:
            allowed = list(allowed)
            unknown = sorted(set(self.data) - set(allowed))
            if unknown:
                raise ConfigError(
                    f"{where}: unknown key '{unknown[0]}' (allowed: {', '.join(allowed)})"
                )

    def has(self, key: str) -> bool:
        return key in self.data

    def _raw(self, key: str, default: Any) -> Any:
        if key in self.data:
            return self.data[key]
        if default is _REQUIRED:
            raise ConfigError(f"{self.where}: missing key '{key}'")
        return default

    def number(
        self,
        key: str,
        default: Any = None,
        *,
        lo: float | None = None,
        hi: float | None = None,
        lo_open: bool = False,
        hi_open: bool = False,
        unit: str = "",
    ) -> float:
        """A finite float in [lo, hi] (open ends if asked); ``default=REQUIRED``: required."""
        value = self._raw(key, default)
        if value is None:
            return None  # type: ignore[return-value]
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(f"{self.where}.{key}: expected a number, got {value!r}")
        value = float(value)
        rng = _range_text(lo, hi, lo_open, hi_open, unit)
        if not math.isfinite(value):
            raise ConfigError(f"{self.where}.{key}: must be finite, allowed {rng}")
        if lo is not None and (value < lo or (lo_open and value == lo)):
            raise ConfigError(f"{self.where}.{key}: {value:g} is out of range, allowed {rng}")
        if hi is not None and (value > hi or (hi_open and value == hi)):
            raise ConfigError(f"{self.where}.{key}: {value:g} is out of range, allowed {rng}")
        return value

    def intervals(self, key: str, default: Any = None) -> tuple[tuple[float, float], ...]:
        """A list of time windows [[t0, t1], ...] (s, 0 <= t0 < t1), sorted; ``default`` when
        absent (REQUIRED: a missing key or an empty list is an error)."""
        raw = self._raw(key, default)
        if key not in self.data:
            return default
        ok = isinstance(raw, list) and (bool(raw) or default is not _REQUIRED) and all(
            isinstance(iv, list) and len(iv) == 2
            and all(isinstance(u, (int, float)) and not isinstance(u, bool) for u in iv)
            and 0 <= iv[0] < iv[1] for iv in raw)
        if not ok:
            what = "a non-empty list" if default is _REQUIRED else "a list"
            raise ConfigError(f"{self.where}.{key}: expected {what} of [t0, t1] with "
                              f"0 <= t0 < t1 (s), got {raw!r}")
        return tuple((float(a), float(b)) for a, b in sorted(raw))

    def integer(self, key: str, default: Any = None, *, lo: int | None = None,
                hi: int | None = None) -> int:
        value = self._raw(key, default)
        if value is None:
            return None  # type: ignore[return-value]
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(f"{self.where}.{key}: expected an integer, got {value!r}")
        if (lo is not None and value < lo) or (hi is not None and value > hi):
            raise ConfigError(
                f"{self.where}.{key}: {value} is out of range, allowed {_range_text(lo, hi)}"
            )
        return value

    def string(self, key: str, default: Any = None, *, choices: Iterable[str] | None = None) -> str:
        value = self._raw(key, default)
        if value is None:
            return None  # type: ignore[return-value]
        if not isinstance(value, str):
            raise ConfigError(f"{self.where}.{key}: expected a string, got {value!r}")
        if choices is not None:
            choices = list(choices)
            if value not in choices:
                raise ConfigError(
                    f"{self.where}.{key}: unknown value '{value}' (allowed: {', '.join(choices)})"
                )
        return value

    def boolean(self, key: str, default: Any = None) -> bool:
        value = self._raw(key, default)
        if not isinstance(value, bool):
            raise ConfigError(f"{self.where}.{key}: expected true or false, got {value!r}")
        return value

    def section(self, key: str, allowed: Iterable[str] | None = None, default: Any = None
                ) -> Section:
        value = self._raw(key, default)
        return Section(value if value is not None else {}, f"{self.where}.{key}", allowed)

    def sections(self, key: str, allowed: Iterable[str] | None = None, default: Any = None
                 ) -> list[Section]:
        value = self._raw(key, default)
        if value is None:
            return []
        if not isinstance(value, list):
            raise ConfigError(f"{self.where}.{key}: expected a list, got {type(value).__name__}")
        return [Section(item, f"{self.where}.{key}[{i}]", allowed) for i, item in enumerate(value)]


class _Required:
    def __repr__(self) -> str:  # pragma: no cover - cosmetic
        return "REQUIRED"


_REQUIRED = _Required()
REQUIRED: Any = _REQUIRED


def _range_text(lo, hi, lo_open=False, hi_open=False, unit="") -> str:
    left = "(" if lo_open or lo is None else "["
    right = ")" if hi_open or hi is None else "]"
    lo_s = "-inf" if lo is None else f"{lo:g}"
    hi_s = "inf" if hi is None else f"{hi:g}"
    return f"{left}{lo_s}, {hi_s}{right}{(' ' + unit) if unit else ''}"


# ---------------------------------------------------------------------------------------------
# Parameters of a config dataclass: declared once, with unit and meaning as the field's metadata
# ---------------------------------------------------------------------------------------------

def param(default, unit: str, doc: str, *, ros: tuple | None = None, node: bool = True,
          lo: float | None = None, hi: float | None = None):
    """A config-dataclass field with its unit and meaning: the one declaration of a parameter.

    ``unit`` ("-" for dimensionless, "" for names and switches) and ``doc`` describe it to the
    node (``train_core.ros.declare_config``: the ROS ParameterDescriptor) and to the reader.
    ``ros = (to_ros, from_ros)`` converts a value a ROS parameter cannot carry (``None``) to a
    sentinel and back. ``node=False``: set by the code (from another parameter), not declared.
    ``lo``/``hi``: the allowed range (inclusive), carried by the ROS descriptor
    (FloatingPointRange / IntegerRange) and listed by ``--help``; the dataclass's own checks
    stay the authority (a range states them, it does not replace them).
    """
    from dataclasses import field

    md = {"unit": unit, "doc": doc, "node": node, "lo": lo, "hi": hi}
    if ros is not None:
        md["ros"] = ros
    return field(default=default, metadata=md)


def param_fields(cls) -> list:
    """The fields of config dataclass ``cls`` a node declares (those made with :func:`param`)."""
    from dataclasses import fields

    return [f for f in fields(cls) if "doc" in f.metadata and f.metadata["node"]]


def describe(f) -> str:
    """One line for a parameter field: "unit, meaning" (or the meaning alone)."""
    unit = f.metadata["unit"]
    return f"{unit}, {f.metadata['doc']}" if unit else f.metadata["doc"]


def param_range(f) -> tuple:
    """(lo, hi) of a parameter field as declared with :func:`param`; None where not stated."""
    return f.metadata.get("lo"), f.metadata.get("hi")


def param_help(classes) -> str:
    """The parameters of config dataclasses ``classes``, one per line, for a node's ``--help``:
    ``name (unit) = default [lo, hi]: meaning``."""
    lines = []
    for cls in classes:
        for f in param_fields(cls):
            to_ros = f.metadata.get("ros", (None, None))[0]
            d = to_ros(f.default) if to_ros else f.default
            d = list(d) if isinstance(d, tuple) else d
            unit = f.metadata["unit"]
            lo, hi = param_range(f)
            rng = "" if lo is None and hi is None else " " + _range_text(lo, hi)
            lines.append(f"  {f.name} ({unit or 'no unit'}) = {d!r}{rng}: {f.metadata['doc']}")
    return "\n".join(lines)


def require(ok: bool, name: str, value, what: str) -> None:
    """Raise ConfigError ``parameter NAME: VALUE WHAT`` unless ``ok`` (validation in one place:
    the config dataclass's ``__post_init__``)."""
    if not ok:
        raise ConfigError(f"parameter {name}: {value!r} {what}")


def require_finite(obj, names, *, above: float = 0.0, strict: bool = True) -> None:
    """``require`` for several numeric fields of ``obj`` at once: each finite and > ``above``
    (>= ``above`` when not ``strict``)."""
    for name in names:
        v = getattr(obj, name)
        ok = math.isfinite(v) and (v > above if strict else v >= above)
        require(ok, name, v, f"must be finite and {'>' if strict else '>='} {above:g}")
