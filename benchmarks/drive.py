"""The benchmark drive of issue #9, written as real YAML files.

N parameters; every 3rd one is 32-bit; one undeclared register after every 40 parameters.
At N=500 that is 667 registers in 13 runs over 679 addresses: 13 FC16 (the optimum) and 13
FC03 per read pass, or 6 FC03 per pass when reads may span the one-register gaps.
Values mix bare numbers, values in another unit (pint) and enumeration labels, as recipes do.
"""

from __future__ import annotations

import os
from typing import Any


def layout(n: int, wide_every: int = 3) -> list[tuple[str, int, str]]:
    """(name, address, type) of each parameter; every ``wide_every``-th one is 32-bit.

    The scaling runs use ``wide_every=4`` at every size: 50,000 parameters then fit in 65,536 registers.
    """
    out = []
    address = 0
    for i in range(n):
        t = "uint32" if i % wide_every == 0 else "uint16"
        out.append((f"P{i:05d}", address, t))
        address += 2 if t == "uint32" else 1
        if i % 40 == 39:
            address += 1  # an undeclared register
    return out


def profile_yaml(n: int, *, max_read_gap: int = 0, profile_id: str = "bench-drive", wide_every: int = 3) -> str:
    lines = [f"profile: {profile_id}", "description: benchmark drive (issue 9)"]
    if max_read_gap:
        lines.append(f"limits: {{max_read_gap: {max_read_gap}}}")
    lines.append("parameters:")
    for i, (name, address, t) in enumerate(layout(n, wide_every)):
        if i % 10 == 9:
            lines.append(f"  {name}: {{register: {address}, type: {t}, values: {{ramp: 0, coast: 1, brake: 2}}}}")
        elif t == "uint32":
            lines.append(f"  {name}: {{register: {address}, type: {t}, unit: s, scale: 0.01, min: 0, max: 6000}}")
        else:
            lines.append(f"  {name}: {{register: {address}, type: {t}, unit: Hz, scale: 0.1, max: 400}}")
    return "\n".join(lines) + "\n"


def value(i: int, t: str, salt: int = 0) -> str:
    """The recipe value of parameter i (salt varies it between runs)."""
    if i % 10 == 9:
        return ("ramp", "coast", "brake")[(i + salt) % 3]
    if t == "uint32":
        v = (i * 7 + salt) % 5000 + 1
        return f"{v * 10} ms" if i % 2 else f"{v} s"
    v = (i * 3 + salt) % 3000 + 1
    return f"{v / 10}"


def recipe_yaml(n: int, profile_path: str, *, salt: int = 0, url: str | None = None, wide_every: int = 3) -> str:
    lines = [f"recipe: bench-{n}", f"profile: {profile_path}"]
    if url:
        lines.append(f'device: {{url: "{url}", unit: 1}}')
    lines.append("parameters:")
    for i, (name, _address, t) in enumerate(layout(n, wide_every)):
        lines.append(f"  {name}: {value(i, t, salt)}")
    return "\n".join(lines) + "\n"


def write(
    directory: str,
    n: int,
    *,
    max_read_gap: int = 0,
    salt: int = 0,
    url: str | None = None,
    name: str | None = None,
    wide_every: int = 3,
) -> dict[str, Any]:
    """Write profile and recipe files into ``directory``; returns their paths."""
    os.makedirs(directory, exist_ok=True)
    base = name or f"drive{n}"
    prof = os.path.join(directory, f"{base}.profile.yaml")
    rec = os.path.join(directory, f"{base}.recipe.yaml")
    with open(prof, "w", encoding="utf-8") as f:
        f.write(profile_yaml(n, max_read_gap=max_read_gap, wide_every=wide_every))
    with open(rec, "w", encoding="utf-8") as f:
        f.write(recipe_yaml(n, os.path.basename(prof), salt=salt, url=url, wide_every=wide_every))
    return {"profile": prof, "recipe": rec}
