"""Parameters of :func:`reblur.detect_changes` from a TOML file (``reblur detect --config``).

One table per options dataclass; each key is a field of it::

    [decision]            # reblur.decide.DecisionParams
    min_area = 50
    illumination = "global"

    [select]              # reblur.select.SelectParams
    max_tries = 2

    [align]               # reblur.align.AlignParams
    method = "features"
    nodata = "none"       # (TOML has no null: "none" for None)

    [rolling]             # reblur.rolling.RollingParams
    n_bands = 8

Values are checked against the type of the field (a number where a number is expected, a
list for a tuple, ...) and then by the dataclass itself; any problem is one
:class:`ConfigError` naming the file, the table and the key.
"""

from __future__ import annotations

import dataclasses
import math
import os
import tomllib
from dataclasses import dataclass, field
from numbers import Integral, Real
from pathlib import Path
from typing import Any

from .align.params import AlignParams
from .decide.params import DecisionParams
from .io import display_path
from .rolling import RollingParams
from .select import SelectParams

__all__ = ["SECTIONS", "ConfigError", "RunConfig", "load_config", "parse_config"]

#: Tables of the file and the dataclass each fills.
SECTIONS: dict[str, type] = {
    "decision": DecisionParams,
    "select": SelectParams,
    "align": AlignParams,
    "rolling": RollingParams,
}
#: Fields that are not options (set by the pipeline or free-form).
_NOT_OPTIONS = {"select": {"extra"}}


class ConfigError(ValueError):
    """A configuration file that cannot be used; the message is one line."""


@dataclass(frozen=True)
class RunConfig:
    """The options a configuration file gives (None: the table is absent).

    ``given`` holds the keys each table sets, so that a command-line flag given
    explicitly can take precedence over them and a default one cannot.
    """

    decision: DecisionParams | None = None
    select: SelectParams | None = None
    align: AlignParams | None = None
    rolling: RollingParams | None = None
    given: dict[str, frozenset[str]] = field(default_factory=dict)
    source: str | None = None

    def sets(self, section: str, key: str) -> bool:
        """Whether the file sets ``[section] key``."""
        return key in self.given.get(section, frozenset())

    def to_dict(self) -> dict[str, Any]:
        """The tables the file gives, with every field (for the report)."""
        out: dict[str, Any] = {"file": self.source}
        for name in SECTIONS:
            v = getattr(self, name)
            if v is not None:
                d = dataclasses.asdict(v)
                out[name] = {k: d[k] for k in sorted(self.given.get(name, ()))}
        return out


def _check_value(section: str, key: str, value: Any, default: Any,
                 optional: bool = False) -> Any:
    """``value`` in the field's type (from its default; ``optional``: None allowed, given
    as ``"none"``), or ConfigError."""
    where = f"[{section}] {key}"
    if optional and isinstance(value, str) and value.lower() == "none":
        return None
    if isinstance(default, bool):
        if not isinstance(value, bool):
            raise ConfigError(f"{where} must be true or false, got {value!r}")
        return value
    if isinstance(default, Integral):
        if isinstance(value, bool) or not isinstance(value, Integral):
            raise ConfigError(f"{where} must be an integer, got {value!r}")
        return int(value)
    if isinstance(default, Real) or default is None:
        if isinstance(value, bool) or not isinstance(value, Real):
            none = ' (or "none")' if optional else ""
            raise ConfigError(f"{where} must be a number{none}, got {value!r}")
        if not math.isfinite(value):  # TOML has nan and inf: never a setting
            raise ConfigError(f"{where} must be a finite number, got {value!r}")
        return float(value)
    if isinstance(default, str):
        if not isinstance(value, str):
            raise ConfigError(f"{where} must be a string, got {value!r}")
        return value
    if isinstance(default, tuple):
        if not isinstance(value, list):
            raise ConfigError(f"{where} must be a list, got {value!r}")
        return tuple(tuple(v) if isinstance(v, list) else v for v in value)
    raise ConfigError(f"{where} cannot be set from a file")


def _fields(section: str) -> dict[str, tuple[Any, bool]]:
    """Each option of the table: its default and whether it may be None."""
    cls = SECTIONS[section]
    skip = _NOT_OPTIONS.get(section, set())
    out = {}
    for f in dataclasses.fields(cls):
        if f.name in skip:
            continue
        default = f.default if f.default is not dataclasses.MISSING else f.default_factory()
        out[f.name] = (default, default is None or "None" in str(f.type))
    return out


def parse_config(data: dict[str, Any], source: str | None = None) -> RunConfig:
    """A :class:`RunConfig` from the parsed TOML ``data``.

    Raises
    ------
    ConfigError
        An unknown table or key, a value of the wrong type, or one the dataclass refuses.
    """
    tables = ", ".join(f"[{s}]" for s in SECTIONS)
    built: dict[str, Any] = {}
    given: dict[str, frozenset[str]] = {}
    for section, table in data.items():
        if section not in SECTIONS:
            what = "table" if isinstance(table, dict) else "key outside a table"
            raise ConfigError(f"unknown {what} {section!r}: the tables are {tables}")
        if not isinstance(table, dict):
            raise ConfigError(f"{section!r} must be a table ([{section}]), not a value")
        fields = _fields(section)
        values = {}
        for key, value in table.items():
            if key not in fields:
                near = [k for k in fields if k.startswith(key[:3])][:4]
                hint = f" (did you mean {', '.join(near)}?)" if near else ""
                raise ConfigError(f"[{section}] unknown key {key!r}{hint}; the keys are the "
                                  f"fields of {SECTIONS[section].__name__}")
            values[key] = _check_value(section, key, value, *fields[key])
        try:
            built[section] = SECTIONS[section](**values)
        except (ValueError, TypeError) as exc:
            msg = " ".join(str(exc).split())
            raise ConfigError(f"[{section}] {msg}") from None
        given[section] = frozenset(values)
    return RunConfig(**built, given=given, source=source)


def load_config(path: str | os.PathLike) -> RunConfig:
    """Read a TOML configuration file (see the module's documentation).

    Raises
    ------
    ConfigError
        The file cannot be read, is not TOML, or holds an unknown table or key or a bad
        value; the message names the file.
    """
    p = Path(path)
    name = display_path(p)
    try:
        data = tomllib.loads(p.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise ConfigError(f"{name}: no such file") from None
    except (OSError, UnicodeDecodeError) as exc:
        why = "not a text file" if isinstance(exc, UnicodeDecodeError) else (
            exc.strerror or str(exc))
        raise ConfigError(f"{name}: {why}") from None
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{name}: not valid TOML: {' '.join(str(exc).split())}") from None
    try:
        return parse_config(data, str(p))
    except ConfigError as exc:
        raise ConfigError(f"{name}: {exc}") from None
