# SPDX-License-Identifier: Apache-2.0
"""A small deterministic TOML writer (stdlib only) and the twin.toml layout.

Only what twin.toml needs: tables, arrays of tables with sub-tables, and
scalar/array values. Key order is the insertion order of the dicts given.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from .numbers import fmt_float


def _str(s: str) -> str:
    out = ['"']
    for ch in s:
        if ch in '"\\':
            out.append("\\" + ch)
        elif ord(ch) < 0x20 or ord(ch) == 0x7F:
            out.append(f"\\u{ord(ch):04X}")
        else:
            out.append(ch)
    out.append('"')
    return "".join(out)


def value(v: Any) -> str:
    """One TOML value: bool, int, float (float32-shortest), str or a list of those."""
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        return fmt_float(v)
    if isinstance(v, str):
        return _str(v)
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(value(x) for x in v) + "]"
    raise TypeError(f"cannot write {type(v).__name__} to TOML")


def _is_table(v: Any) -> bool:
    return isinstance(v, dict)


def _is_table_array(v: Any) -> bool:
    return isinstance(v, list) and bool(v) and all(isinstance(x, dict) for x in v)


def _emit(lines: list[str], prefix: str, table: dict, header: str | None) -> None:
    if header is not None:
        if lines:
            lines.append("")
        lines.append(header)
    for k, v in table.items():
        if not (_is_table(v) or _is_table_array(v)):
            lines.append(f"{k} = {value(v)}")
    for k, v in table.items():
        key = f"{prefix}{k}"
        if _is_table(v):
            _emit(lines, key + ".", v, f"[{key}]")
        elif _is_table_array(v):
            for item in v:
                _emit(lines, key + ".", item, f"[[{key}]]")


def dumps(data: dict) -> str:
    """Serialise nested dicts/lists to TOML text, deterministically (LF, trailing newline)."""
    lines: list[str] = []
    _emit(lines, "", data, None)
    return "\n".join(lines) + "\n"


def write_twin_toml(path: Path, data: dict) -> None:
    """Write ``data`` (built by the exporter in twin.toml key order) to ``path``."""
    Path(path).write_bytes(dumps(data).encode("utf-8"))
