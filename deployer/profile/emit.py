"""Profile files written by the importers: one line per parameter, so a problem in the result
can be traced back to the row (or model point) it came from."""

from __future__ import annotations

import json
import os
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from decimal import Decimal
from typing import Any

from ..load.diagnostics import Diagnostic, InputError
from .loader import load_profile_file
from .model import Profile


@dataclass(frozen=True)
class Origin:
    """Where an imported parameter came from (a CSV row and cell, a model point)."""

    path: str
    line: int
    col: int = 1


@dataclass
class Draft:
    """A profile being imported: header keys, parameters and tables in source order, and their origins."""

    header: dict[str, Any]
    parameters: list[tuple[str, dict[str, Any], Origin]]
    tables: list[tuple[str, dict[str, Any], Origin]]

    def text(self, comment: str = "") -> tuple[str, dict[int, Origin]]:
        """The profile as YAML, and the source of each generated line."""
        lines = [f"# {c}" for c in comment.splitlines()] if comment else []
        origins: dict[int, Origin] = {}
        for k, v in self.header.items():
            lines.append(f"{k}: {_flow(v)}")
        for section, items in (("parameters", self.parameters), ("tables", self.tables)):
            if not items:
                continue
            lines.append(f"{section}:")
            for name, spec, origin in items:
                if section == "tables":
                    head = {k: v for k, v in spec.items() if k != "fields"}
                    lines.append(f"  {name}: {{{', '.join(f'{k}: {_flow(v)}' for k, v in head.items())}, fields: {{")
                    origins[len(lines)] = origin
                    for fname, fspec in spec["fields"].items():
                        lines.append(f"    {fname}: {_flow(fspec)},")
                        origins[len(lines)] = origin
                    lines.append("  }}")
                    continue
                lines.append(f"  {name}: {_flow(spec)}")
                origins[len(lines)] = origin
        return "\n".join(lines) + "\n", origins


def _flow(v: Any) -> str:
    """A value in YAML flow style (JSON is YAML); registers in hex like the manuals."""
    if isinstance(v, Mapping):
        return "{" + ", ".join(f"{k}: {_hex(v[k]) if k == 'register' else _flow(v[k])}" for k in v) + "}"
    if isinstance(v, float):  # YAML reads 1e-07 as text: write 0.0000001
        return format(Decimal(repr(v)), "f")
    return json.dumps(v, ensure_ascii=False)


def _hex(v: Any) -> str:
    return f"0x{v:04X}" if isinstance(v, int) else json.dumps(v)


def check(draft: Draft, out_path: str, comment: str = "") -> tuple[str, Profile]:
    """The draft's text, loaded as a profile; its problems point at the source rows."""
    text, origins = draft.text(comment)
    try:
        prof = load_profile_file(out_path, text)
    except InputError as e:
        raise InputError(traced(e.diagnostics, origins, out_path)) from None
    return text, prof


def traced(diagnostics: Sequence[Diagnostic], origins: Mapping[int, Origin], out_path: str) -> list[Diagnostic]:
    out = []
    for d in diagnostics:
        o = origins.get(d.line) if os.path.abspath(d.path) == os.path.abspath(out_path) else None
        if o is None:
            out.append(d)
            continue
        # "... (line N)" names another generated line: say its source line instead
        message = re.sub(r"\bline (\d+)", lambda m: f"line {origins[int(m[1])].line}" if int(m[1]) in origins
                         else m[0], d.message)
        out.append(Diagnostic(o.path, o.line, o.col, message))
    return out
