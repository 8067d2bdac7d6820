"""Mutation fuzzing of the file loaders and importers: every mutated file must end in exit 0 or 1, never a crash.

    python -m tests.fuzz --files 20000 --seconds 600      # `make fuzz`
    python -m tests.fuzz --files 1500 --seconds 40        # what `make test` runs (tests/test_hostile.py)
    python -m tests.fuzz --kinds csv,xlsx,sunspec         # the importers only

The corpus is every YAML file of the repository (examples, built-in profiles, the malformed-file
corpus); each mutant is one to three edits of one of them (bytes flipped, lines dropped,
duplicated or swapped, YAML syntax, aliases, tags, huge numbers, deep brackets, odd Unicode
inserted). Each is checked in-process with ``deployer validate`` and, when it is a valid recipe,
``deployer plan``. The importers get the same edits (and their formats' own syntax) on register
lists (``profiles import csv``; the CSV files of tests/bad/import and vendor sheets made here),
on the sheet XML of workbooks (``import xlsx``) and on SunSpec model files (``import sunspec``;
pysunspec2's models and tests/bad/import's). Printed as JSON: files tried (per kind), crashes
(with the file kept), slowest file, peak memory. Exit 1 on any crash.
"""

from __future__ import annotations

import argparse
import contextlib
import csv
import io
import json
import os
import random
import shutil
import sys
import tempfile
import time
import traceback
from pathlib import Path
from xml.sax.saxutils import escape

ROOT = Path(__file__).resolve().parent.parent
TOKENS = [
    "&a ",
    "*a",
    "[",
    "]",
    "{",
    "}",
    ": ",
    "- ",
    "!!python/object:os.system ",
    "!!binary ",
    "<<: ",
    "? ",
    "9" * 400,
    "1e999999999",
    "0x",
    "-",
    "\t",
    "\u2028",
    "\x00",
    "\ufeff",
    "'",
    '"',
    "#",
    "|",
    ">",
    "%YAML 1.2\n",
    "---\n",
    "...\n",
    "~",
    "null",
    "yes",
    "1:30",
    ".nan",
    " ms",
    " degC",
    " furlong",
    "{raw: 1}",
    "[" * 300,
    "extends: /dev/zero\n",
    "extends: fuzz-0.yaml\n",
    "profile: ../nope.yaml\n",
    "é",
    "\\u0000",
    "010",
    "0o17",
    "-08",
    "1e-30",
    "device: {url: 'tcp://[::1'}\n",
    "device: {url: 'tcp://u:p@h#f'}\n",
    "device: {url: 'tls://h?ca=/dev/zero&ca=x'}\n",
    "tcp://",
    "rtu+tcp://",
    "?timeout=",
    "&retries=",
]


CSV_TOKENS = [
    ",",
    ";",
    "\t",
    '"',
    '""',
    "\n",
    "\r\n",
    "0x",
    "FFh",
    "-1",
    "3,000",
    "0,5",
    "1.000,5",
    "inf",
    "NaN",
    "1e-999999999",
    "9" * 400,
    "0.01 s",
    "0 to 40000",
    "0...100 %",
    "0-400.00",
    "10 furlong",
    "=1/10",
    "'=cmd",
    "@SUM(1)",
    "U16",
    "FLOAT",
    "STRING",
    "BOOL",
    "RW",
    "0=ramp;1=coast",
    "3..5",
    "\x00",
    "é",
    "\u2028",
    "X: {register: 7}",
    "," * 300,
]
XML_TOKENS = [
    "<",
    ">",
    "</row>",
    "<row>",
    '<c r="XFD1">',
    "<c>",
    "</c>",
    "<v>",
    "</v>",
    "<f>1/10</f>",
    '<c t="s"><v>99',
    '<c t="inlineStr"><is><t>',
    "</t></is>",
    'r="1048576"',
    'r="A0"',
    "&amp;",
    "&#0;",
    "<!DOCTYPE x>",
    "\x00",
    "é",
    "9" * 400,
]
JSON_TOKENS = [
    "{",
    "}",
    "[",
    "]",
    ",",
    ":",
    '"',
    '"count": 100000000',
    '"count": -5',
    '"count": 0',
    '"count": "N"',
    '"sf": 1000000000',
    '"sf": "Nope_SF"',
    '"size": 0',
    '"size": 99999',
    '"type": "string"',
    '"type": "pad"',
    '"name": "X: {register: 7}"',
    '"value": 1e999',
    "null",
    "true",
    "9" * 400,
    "\\u0000",
]


def vendor_csv(rnd: random.Random, rows: int = 12) -> str:
    """A vendor register list of the kinds issue #22 describes (units in cells, ranges, odd headers)."""
    head = rnd.choice(
        [
            ["name", "address", "type", "unit", "scale", "min", "max", "access"],
            ["Parameter", "Reg", "Data Type", "Resolution", "Setting range", "R/W", "Remark"],
            ["Tag", "Modbus address", "Format", "Units", "Factor", "Low", "High", "Values", "Bits"],
        ]
    )
    sep = rnd.choice([",", ";", "\t"])
    out = [sep.join(head)]
    for i in range(rows):
        cells = {
            "name": f"P{i:03d}",
            "parameter": f"P{i:03d}",
            "tag": f"P{i:03d}",
            "address": str(100 + i),
            "reg": f"{100 + i:04X}h",
            "modbus address": str(40001 + i),
            "type": "U16",
            "data type": "S16",
            "format": "FLOAT",
            "unit": "s",
            "units": "Hz",
            "scale": "0.1",
            "resolution": "0.01 s",
            "factor": "1",
            "min": "0",
            "max": "100",
            "setting range": "0 to 400.00",
            "low": "-10",
            "high": "10",
            "access": "RW",
            "r/w": "R",
            "remark": "x",
            "values": "0=off;1=on",
            "bits": "",
        }
        out.append(sep.join(cells.get(h.lower(), "") for h in head))
    return "\n".join(out) + "\n"


def import_corpus() -> dict[str, list[tuple[str, str]]]:
    """Seeds of the importers: CSV register lists, sheet XML of workbooks, SunSpec model files."""
    rnd = random.Random(0)
    csvs = [(f"vendor-{i}.csv", vendor_csv(rnd)) for i in range(6)]
    csvs += [
        (p.name, p.read_text(encoding="utf-8", errors="replace"))
        for p in sorted((ROOT / "tests" / "bad" / "import").glob("*.csv"))
        if p.stat().st_size < 20_000
    ]
    sheets = []
    for name, text in csvs[:6]:
        sep = max(",;\t", key=text.splitlines()[0].count)
        rows = list(csv.reader(io.StringIO(text), delimiter=sep))
        sheets.append(
            (
                name.replace(".csv", ".xlsx"),
                "".join(
                    f'<row r="{r}">'
                    + "".join(
                        f'<c r="{chr(65 + c)}{r}" t="inlineStr"><is><t>{escape(cell)}</t></is></c>'
                        for c, cell in enumerate(row)
                    )
                    + "</row>\n"
                    for r, row in enumerate(rows, 1)
                ),
            )
        )
    bad = ROOT / "tests" / "bad" / "import"
    models = [(p.name, p.read_text(encoding="utf-8")) for p in sorted(bad.glob("*.json"))]
    try:
        from deployer.profile.importers.sunspec import models_dir

        models += [
            (p.name, p.read_text(encoding="utf-8"))
            for p in sorted(Path(models_dir()).glob("model_*.json"))
            if p.stat().st_size < 12_000
        ][:40]
    except Exception:  # pysunspec2 is an optional extra
        pass
    return {"csv": csvs, "xlsx": sheets, "sunspec": models}


def corpus() -> list[tuple[str, str]]:
    out = []
    for pattern in ("recipes/**/*.yaml", "deployer/profiles/*.yaml", "tests/bad/**/*.yaml"):
        for p in sorted(ROOT.glob(pattern)):
            if p.stat().st_size < 20_000:
                out.append((p.name, p.read_text(encoding="utf-8", errors="replace")))
    return out


def mutate(text: str, rnd: random.Random, tokens: list[str] = TOKENS) -> str:
    for _ in range(rnd.randint(1, 3)):
        lines = text.splitlines(keepends=True) or ["\n"]
        op = rnd.randrange(7)
        if op == 0 and text:  # flip a character
            i = rnd.randrange(len(text))
            text = text[:i] + chr(rnd.choice([rnd.randrange(32, 127), rnd.randrange(0, 0x3000)])) + text[i + 1 :]
        elif op == 1:  # drop a line
            del lines[rnd.randrange(len(lines))]
            text = "".join(lines)
        elif op == 2:  # duplicate a line
            i = rnd.randrange(len(lines))
            lines.insert(i, lines[i])
            text = "".join(lines)
        elif op == 3:  # swap two lines
            i, j = rnd.randrange(len(lines)), rnd.randrange(len(lines))
            lines[i], lines[j] = lines[j], lines[i]
            text = "".join(lines)
        elif op == 4:  # insert a token
            i = rnd.randrange(len(text) + 1)
            text = text[:i] + rnd.choice(tokens) + text[i:]
        elif op == 5:  # replace a value after ': '
            i = text.find(": ", rnd.randrange(len(text) + 1))
            if i >= 0:
                end = text.find("\n", i)
                end = len(text) if end < 0 else end
                text = text[: i + 2] + rnd.choice([*tokens, "10 s", "0", "-1", "65536", "coast"]) + text[end:]
        else:  # re-indent a line
            i = rnd.randrange(len(lines))
            lines[i] = " " * rnd.randrange(6) + lines[i].lstrip(" ")
            text = "".join(lines)
    return text


def run_cli(args: list[str]) -> int:
    from deployer.cli import main

    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        try:
            main(args)
        except SystemExit as e:
            code = e.code if isinstance(e.code, int) else 1
        else:
            code = 0
    if "Traceback" in err.getvalue():
        raise RuntimeError(f"a traceback was printed:\n{err.getvalue()[-2000:]}")
    return code


def _import_one(kind: str, text: str, work: Path, n: int) -> Path:
    """The mutant as the file the importer reads (a workbook around a sheet's XML)."""
    if kind == "xlsx":
        from tests.hostile_imports import NS, write_xlsx

        path = work / f"fuzz-{n % 50}.xlsx"
        sheet = f'<?xml version="1.0" encoding="UTF-8"?>\n<worksheet {NS}><sheetData>{text}</sheetData></worksheet>'
        write_xlsx(path, [sheet.encode("utf-8", errors="surrogatepass")])
        return path
    path = work / f"fuzz-{n % 50}.{'json' if kind == 'sunspec' else 'csv'}"
    path.write_text(text, encoding="utf-8", errors="surrogatepass")
    return path


def fuzz(
    files: int,
    seconds: float,
    seed: int,
    keep: str | None = None,
    kinds: tuple[str, ...] = ("yaml", "csv", "xlsx", "sunspec"),
) -> dict[str, object]:
    rnd = random.Random(seed)
    seeds = corpus() if "yaml" in kinds else []
    imports = {k: v for k, v in import_corpus().items() if k in kinds and v}
    tokens = {"csv": CSV_TOKENS, "xlsx": XML_TOKENS, "sunspec": JSON_TOKENS}
    per_kind = dict.fromkeys(kinds, 0)
    imported = 0
    if keep:
        os.makedirs(keep, exist_ok=True)
    work = Path(tempfile.mkdtemp(prefix="deployer-fuzz-"))
    shutil.copytree(ROOT / "tests" / "bad" / "lib", work / "lib")
    for p in ROOT.glob("recipes/examples/*.yaml"):  # recipes that extend their neighbours
        shutil.copy(p, work / p.name)
    crashes: list[dict[str, str]] = []
    tried = valid = 0
    slowest = (0.0, "")
    start = time.monotonic()
    try:
        while tried < files and time.monotonic() - start < seconds:
            # every other file a YAML one (the loaders), the rest shared by the importers
            kind = "yaml" if seeds and (not imports or tried % 2 == 0) else rnd.choice(sorted(imports))
            per_kind[kind] += 1
            tried += 1
            t0 = time.monotonic()
            if kind != "yaml":
                name, text = rnd.choice(imports[kind])
                path = _import_one(kind, mutate(text, rnd, tokens[kind]), work, tried)
                try:
                    args = ["profiles", "import", kind, str(path)] + (["--id", "f"] if kind != "sunspec" else [])
                    code = run_cli(args)
                    if code not in (0, 1):
                        raise RuntimeError(f"profiles import {kind} exited {code}")
                    imported += code == 0
                except Exception as e:  # a crash: keep the file
                    kept = Path(keep or work) / f"crash-{len(crashes)}{path.suffix}"
                    kept.parent.mkdir(parents=True, exist_ok=True)
                    shutil.copy(path, kept)
                    crashes.append(
                        {
                            "seed_file": name,
                            "kept": str(kept),
                            "error": "".join(traceback.format_exception_only(type(e), e)).strip()[-500:],
                        }
                    )
                dt = time.monotonic() - t0
                if dt > slowest[0]:
                    slowest = (dt, name)
                continue
            name, text = seeds[rnd.randrange(len(seeds))]
            path = work / f"fuzz-{tried % 50}.yaml"
            path.write_text(mutate(text, rnd), encoding="utf-8", errors="surrogatepass")
            try:
                code = run_cli(["validate", str(path)])
                if code not in (0, 1):
                    raise RuntimeError(f"validate exited {code}")
                if code == 0 and "recipe" in path.read_text(errors="replace")[:200]:
                    valid += 1
                    code = run_cli(["plan", str(path)])
                    if code not in (0, 1):
                        raise RuntimeError(f"plan exited {code}")
            except Exception as e:  # a crash: keep the file
                kept = Path(keep or work) / f"crash-{len(crashes)}.yaml"
                kept.parent.mkdir(parents=True, exist_ok=True)
                shutil.copy(path, kept)
                crashes.append(
                    {
                        "seed_file": name,
                        "kept": str(kept),
                        "error": "".join(traceback.format_exception_only(type(e), e)).strip()[-500:],
                    }
                )
            dt = time.monotonic() - t0
            if dt > slowest[0]:
                slowest = (dt, name)
                if keep:
                    shutil.copy(path, Path(keep) / "slowest.yaml")
    finally:
        if not crashes:
            shutil.rmtree(work, ignore_errors=True)
    return {
        "files_tried": tried,
        "per_kind": per_kind,
        "valid_recipes_planned": valid,
        "mutants_imported": imported,
        "crashes": len(crashes),
        "crash_details": crashes,
        "seconds": round(time.monotonic() - start, 1),
        "slowest_file_seconds": round(slowest[0], 3),
        "slowest_seed": slowest[1],
        "peak_rss_mb": round(_peak_rss_kb() / 1024, 1),
        "seed": seed,
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--files", type=int, default=20_000)
    ap.add_argument("--seconds", type=float, default=600)
    ap.add_argument("--seed", type=int, default=int(os.environ.get("FUZZ_SEED", "1")))
    ap.add_argument("--keep", help="directory for crashing files")
    ap.add_argument(
        "--kinds",
        default="yaml,csv,xlsx,sunspec",
        help="what to fuzz: yaml (validate, plan), csv, xlsx, sunspec (profiles import)",
    )
    args = ap.parse_args(argv)
    res = fuzz(args.files, args.seconds, args.seed, args.keep, tuple(k.strip() for k in args.kinds.split(",")))
    print(json.dumps(res, indent=2))
    return 1 if res["crashes"] else 0


def _peak_rss_kb() -> int:
    """This process's peak resident memory: ru_maxrss (POSIX), PeakWorkingSetSize (Windows)."""
    if sys.platform == "win32":
        import ctypes

        counters = (ctypes.c_size_t * 10)()  # PROCESS_MEMORY_COUNTERS: cb first, PeakWorkingSetSize third
        counters[0] = ctypes.sizeof(counters)
        k32 = ctypes.windll.kernel32
        k32.GetCurrentProcess.restype = ctypes.c_void_p
        k32.K32GetProcessMemoryInfo(ctypes.c_void_p(k32.GetCurrentProcess()), counters, ctypes.sizeof(counters))
        return int(counters[2]) // 1024
    import resource

    return int(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss)


if __name__ == "__main__":
    sys.exit(main())
