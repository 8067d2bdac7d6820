"""Mutation fuzzing of the file loaders: every mutated file must end in exit 0 or 1, never a crash.

    python -m tests.fuzz --files 20000 --seconds 600      # `make fuzz`
    python -m tests.fuzz --files 1500 --seconds 40        # what `make test` runs (tests/test_hostile.py)

The corpus is every YAML file of the repository (examples, built-in profiles, the malformed-file
corpus); each mutant is one to three edits of one of them (bytes flipped, lines dropped,
duplicated or swapped, YAML syntax, aliases, tags, huge numbers, deep brackets, odd Unicode
inserted). Each is checked in-process with ``deployer validate`` and, when it is a valid recipe,
``deployer plan``. Printed as JSON: files tried, crashes (with the file kept), slowest file,
peak memory. Exit 1 on any crash.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import os
import random
import resource
import shutil
import sys
import tempfile
import time
import traceback
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
TOKENS = ["&a ", "*a", "[", "]", "{", "}", ": ", "- ", "!!python/object:os.system ", "!!binary ", "<<: ", "? ",
          "9" * 400, "1e999999999", "0x", "-", "\t", "\u2028", "\x00", "\ufeff", "'", '"', "#", "|", ">", "%YAML 1.2\n",
          "---\n", "...\n", "~", "null", "yes", "1:30", ".nan", " ms", " degC", " furlong", "{raw: 1}",
          "[" * 300, "extends: /dev/zero\n", "extends: fuzz-0.yaml\n", "profile: ../nope.yaml\n", "é", "\\u0000",
          "010", "0o17", "-08", "1e-30", "device: {url: 'tcp://[::1'}\n", "device: {url: 'tcp://u:p@h#f'}\n",
          "device: {url: 'tls://h?ca=/dev/zero&ca=x'}\n", "tcp://", "rtu+tcp://", "?timeout=", "&retries="]


def corpus() -> list[tuple[str, str]]:
    out = []
    for pattern in ("recipes/**/*.yaml", "deployer/profiles/*.yaml", "tests/bad/**/*.yaml"):
        for p in sorted(ROOT.glob(pattern)):
            if p.stat().st_size < 20_000:
                out.append((p.name, p.read_text(encoding="utf-8", errors="replace")))
    return out


def mutate(text: str, rnd: random.Random) -> str:
    for _ in range(rnd.randint(1, 3)):
        lines = text.splitlines(keepends=True) or ["\n"]
        op = rnd.randrange(7)
        if op == 0 and text:  # flip a character
            i = rnd.randrange(len(text))
            text = text[:i] + chr(rnd.choice([rnd.randrange(32, 127), rnd.randrange(0, 0x3000)])) + text[i + 1:]
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
            text = text[:i] + rnd.choice(TOKENS) + text[i:]
        elif op == 5:  # replace a value after ': '
            i = text.find(": ", rnd.randrange(len(text) + 1))
            if i >= 0:
                end = text.find("\n", i)
                end = len(text) if end < 0 else end
                text = text[: i + 2] + rnd.choice([*TOKENS, "10 s", "0", "-1", "65536", "coast"]) + text[end:]
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


def fuzz(files: int, seconds: float, seed: int, keep: str | None = None) -> dict[str, object]:
    rnd = random.Random(seed)
    seeds = corpus()
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
            name, text = seeds[rnd.randrange(len(seeds))]
            path = work / f"fuzz-{tried % 50}.yaml"
            path.write_text(mutate(text, rnd), encoding="utf-8", errors="surrogatepass")
            tried += 1
            t0 = time.monotonic()
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
                crashes.append({"seed_file": name, "kept": str(kept),
                                "error": "".join(traceback.format_exception_only(type(e), e)).strip()[-500:]})
            dt = time.monotonic() - t0
            if dt > slowest[0]:
                slowest = (dt, name)
                if keep:
                    shutil.copy(path, Path(keep) / "slowest.yaml")
    finally:
        if not crashes:
            shutil.rmtree(work, ignore_errors=True)
    return {"files_tried": tried, "valid_recipes_planned": valid, "crashes": len(crashes), "crash_details": crashes,
            "seconds": round(time.monotonic() - start, 1), "slowest_file_seconds": round(slowest[0], 3),
            "slowest_seed": slowest[1],
            "peak_rss_mb": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1), "seed": seed}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--files", type=int, default=20_000)
    ap.add_argument("--seconds", type=float, default=600)
    ap.add_argument("--seed", type=int, default=int(os.environ.get("FUZZ_SEED", "1")))
    ap.add_argument("--keep", help="directory for crashing files")
    args = ap.parse_args(argv)
    res = fuzz(args.files, args.seconds, args.seed, args.keep)
    print(json.dumps(res, indent=2))
    return 1 if res["crashes"] else 0


if __name__ == "__main__":
    sys.exit(main())
