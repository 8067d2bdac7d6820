"""Compare installed versions (``pip freeze`` on stdin) with constraints.txt, or write them into it.

    pip freeze --all --exclude-editable | python tools/versions.py constraints.txt          # what changed
    pip freeze --all --exclude-editable | python tools/versions.py --write constraints.txt  # pin them

``make test-latest`` prints the comparison before running the suite on the newest releases, so a
failure there comes with the list of what moved; ``make constraints`` pins what passed.
"""

from __future__ import annotations

import argparse
import re
import sys

HEADER = (
    "# Versions the test suite passed with (make test installs these; make test-latest tries the newest).\n"
    "# Regenerate with: make test-latest && make constraints   (commit the file once make test passes)\n"
)
_PIN = re.compile(r"^([A-Za-z0-9][A-Za-z0-9._-]*)==(\S+)")


def pins(lines: list[str]) -> dict[str, tuple[str, str]]:
    """name (normalised as PEP 503 does) -> (name as written, version), for every ``name==version`` line."""
    out: dict[str, tuple[str, str]] = {}
    for line in lines:
        m = _PIN.match(line.strip())
        if m:
            out[re.sub(r"[-_.]+", "-", m.group(1)).lower()] = (m.group(1), m.group(2))
    return out


def changes(old: dict[str, tuple[str, str]], new: dict[str, tuple[str, str]]) -> list[str]:
    out = []
    for key in sorted(old.keys() | new.keys()):
        if key not in new:
            out.append(f"  {old[key][0]} {old[key][1]} -> (not installed)")
        elif key not in old:
            out.append(f"  {new[key][0]} (not pinned) -> {new[key][1]}")
        elif old[key][1] != new[key][1]:
            out.append(f"  {new[key][0]} {old[key][1]} -> {new[key][1]}")
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("constraints")
    ap.add_argument("--write", action="store_true", help="replace the file with the versions read on stdin")
    args = ap.parse_args(argv)
    new = pins(sys.stdin.read().splitlines())
    if args.write:
        with open(args.constraints, "w", encoding="utf-8") as f:
            f.write(HEADER + "".join(f"{name}=={version}\n" for name, version in (new[k] for k in sorted(new))))
        print(f"{args.constraints}: {len(new)} pinned versions written")
        return 0
    with open(args.constraints, encoding="utf-8") as f:
        old = pins(f.read().splitlines())
    moved = changes(old, new)
    print(f"newest releases against {args.constraints}: " + (f"{len(moved)} differ" if moved else "no change"))
    if moved:
        print("\n".join(moved))
    return 0


if __name__ == "__main__":
    sys.exit(main())
