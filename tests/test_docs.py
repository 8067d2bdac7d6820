"""The reference docs: generated from the schemas, never stale, every example valid."""

from __future__ import annotations

import json
import re
import tomllib
from pathlib import Path

import jsonschema
import pytest
import yaml

from deployer.cli import docgen
from deployer.cli.files import validate_file
from deployer.load import schema
from deployer.profile import Limits
from deployer.transport.urls import _OPTIONS, DEFAULT_PORTS, NUMERIC_OPTIONS, SERIAL_DEFAULTS, option_facts
from tests.helpers import cli

ROOT = Path(__file__).parent.parent
DOCS = ROOT / "docs"
# a fenced block preceded by <!-- example: partial --> is an excerpt; <!-- example: file=NAME --> names
# the file it is written to (so recipes can name the profiles of the same page by path)
FENCE = re.compile(r"(?:<!--\s*example:\s*(?P<mark>[^>]*?)\s*-->\s*\n)?```(?P<lang>yaml|json)\n(?P<body>.*?)```", re.S)


@pytest.mark.parametrize("name", docgen.SCHEMAS)
def test_every_schema_property_has_a_description(name: str) -> None:
    assert docgen.undescribed(name) == []


def test_undescribed_finds_a_missing_description(monkeypatch: pytest.MonkeyPatch) -> None:
    bare = {
        "description": "x",
        "type": "object",
        "properties": {"a": {"type": "integer"}},
        "$defs": {"d": {"type": "object", "additionalProperties": {"type": "string"}}},
    }
    monkeypatch.setattr(schema, "schema", lambda name: bare)
    assert docgen.undescribed("any") == ["#/properties/a", "#/$defs/d/additionalProperties", "#/$defs/d"]


def test_committed_reference_is_not_stale(capsys: pytest.CaptureFixture[str]) -> None:
    assert docgen.stale_pages(str(DOCS / "reference")) == [], "run: make docs"
    code, _, err = cli(capsys, "docs", "--check", "--out", str(DOCS / "reference"))
    assert (code, err) == (0, "")


def test_docs_command_writes_and_checks(capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    out = tmp_path / "ref"
    code, _, err = cli(capsys, "docs", "--check", "--out", str(out))
    assert code == 1 and f"{out / 'profile.md'}: stale" in err
    code, _, err = cli(capsys, "docs", "--out", str(out))
    assert code == 0 and err == f"8 pages updated in {out}\n"
    assert sorted(p.name for p in out.iterdir()) == [
        "fleetplan.md",
        "inventory.md",
        "plan.md",
        "profile.md",
        "recipe.md",
        "report.md",
        "snapshot.md",
        "users.md",
    ]
    (out / "recipe.md").write_text("edited by hand\n")
    code, _, err = cli(capsys, "docs", "--check", "--out", str(out))
    assert code == 1 and err == f"{out / 'recipe.md'}: stale (run: deployer docs --out {out})\n"


def test_every_key_is_documented_with_its_facts() -> None:
    page = docgen.render_page("profile")
    for key in docgen.schema_keys("profile"):
        assert f"### `{key.path}`" in page
        assert key.description, key.path
    assert "optional · integer · default `256` · allowed: 11..256" in page
    assert "Example: `max_frame_bytes: 64`" in page


def test_schema_defaults_are_the_code_defaults() -> None:
    props = schema.schema("profile")["properties"]["limits"]["properties"]
    for name, spec in props.items():
        assert spec["default"] == getattr(Limits(), name), name


def test_explain(capsys: pytest.CaptureFixture[str]) -> None:
    code, out, _ = cli(capsys, "explain", "max_frame_bytes")
    assert code == 0 and out.startswith("profile: limits.max_frame_bytes\n  optional · integer · default 256")
    code, out, _ = cli(capsys, "explain", "recipe:device.unit")
    assert code == 0 and out.splitlines()[0] == "recipe: device.unit" and "profile:" not in out
    code, _, err = cli(capsys, "explain", "max_frame")
    assert code == 1 and err == "error: no key 'max_frame' in any schema; did you mean max_frame_bytes?\n"
    code, out, _ = cli(capsys, "explain", "baudrate")
    assert code == 0 and out == (
        "url: baudrate\n  device URL option (rtu, ascii) · default 19200 · allowed: "
        "50..4000000\n  Every scheme and option, with what they mean: docs/urls.md\n"
    )
    code, out, _ = cli(capsys, "explain", "timeout")  # an inventory key and a URL option
    assert code == 0 and "inventory: defaults.timeout" in out and "url: timeout\n" in out
    # a manual's word for what is called otherwise here points at our key
    code, out, _ = cli(capsys, "explain", "resolution")
    assert code == 0 and out.startswith(
        "'resolution' is not a key here: a parameter's resolution (a manual's "
        "'0.01 s units') is its scale.\n\nprofile: parameters.PARAM.scale\n"
    )
    code, out, _ = cli(capsys, "explain", "slave")
    assert code == 0 and "\n\nrecipe: device.unit\n" in out and "profile:" not in out


def _blocks(page: Path) -> list[tuple[str, str, str]]:
    return [(m["mark"] or "", m["lang"], m["body"]) for m in FENCE.finditer(page.read_text())]


PAGES = sorted([*DOCS.rglob("*.md"), ROOT / "README.md"])


def test_examples_are_found() -> None:
    total = sum(len(_blocks(p)) for p in PAGES)
    checked = sum(1 for p in PAGES for mark, _, _ in _blocks(p) if mark != "partial")
    assert total >= 10 and checked >= 8


@pytest.mark.parametrize("page", PAGES, ids=[str(p.relative_to(ROOT)) for p in PAGES])
def test_every_example_in_the_docs_validates(page: Path, tmp_path: Path) -> None:
    """Each complete YAML/JSON block is written to a file and checked as `deployer validate` would."""
    files: list[Path] = []
    for i, (mark, lang, body) in enumerate(_blocks(page)):
        if mark == "partial":
            continue
        name = mark.removeprefix("file=") if mark.startswith("file=") else f"example{i}.{lang}"
        path = tmp_path / name
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(body)
        files.append(path)
    for path in files:  # after writing them all: a recipe may name a profile of the same page
        data = yaml.safe_load(path.read_text())
        if isinstance(data, dict) and str(data.get("schema", "")).startswith("deployer.report/"):
            jsonschema.validate(data, schema.schema("report"))
        else:
            validate_file(str(path))


def test_url_page_covers_every_scheme_and_option() -> None:
    text = (DOCS / "urls.md").read_text()
    for scheme, options in _OPTIONS.items():
        assert f"`{scheme}://" in text, scheme
        for opt in options:
            assert f"`{opt}`" in text, (scheme, opt)
    for scheme, port in DEFAULT_PORTS.items():
        assert f"{scheme}://HOST[:PORT]` | {port}" in text
    line = SERIAL_DEFAULTS
    assert f"{line.baudrate} baud, {line.bytesize} data bits, parity {line.parity}, {line.stopbits} stop bit" in text
    # each numeric option's row: default and range as the code has them
    for opt in NUMERIC_OPTIONS:
        _, default, allowed = option_facts(opt)
        assert f"| `{opt}` | {default} | {allowed} |" in text, opt
    assert f"| `parity` | {line.parity} |" in text and f"| `verify` | {option_facts('verify')[1]} |" in text


def test_report_example_matches_the_exit_code_rules() -> None:
    ex = schema.schema("report")["examples"][0]
    assert json.loads(json.dumps(ex))["summary"]["partial"] == 1


def test_profiles_new_writes_a_skeleton_that_validates(capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    path = tmp_path / "pid-ctrl.yaml"
    code, _, err = cli(capsys, "profiles", "new", str(path))
    assert code == 0 and err == f"wrote {path}: fill it in from the manual, then run: deployer validate {path}\n"
    text = path.read_text()
    assert text.count("\n#") > 10 and "profile: pid-ctrl\n" in text
    assert validate_file(str(path)) == "profile pid-ctrl: 1 parameter"
    code, _, err = cli(capsys, "profiles", "new", str(path))
    assert code == 1 and err == f"error: {path} exists; pass --force to overwrite it\n"
    code, _, _ = cli(capsys, "profiles", "new", str(path), "--force", "--id", "other")
    assert code == 0 and validate_file(str(path)) == "profile other: 1 parameter"
    code, _, err = cli(capsys, "profiles", "new", str(tmp_path / "my drive.yaml"))
    assert code == 1 and "'my drive' is not a profile id" in err
    # every commented-out key, uncommented, is still a valid profile key
    lines = [re.sub(r"^(\s*)# ?(\s*)([a-z_]+:(\s.*)?|- \{.*)$", r"\1\2\3", ln) for ln in text.splitlines()]
    assert sum(a != b for a, b in zip(lines, text.splitlines(), strict=True)) >= 20
    full = tmp_path / "full.yaml"
    full.write_text("\n".join(lines) + "\n")
    assert validate_file(str(full)) == "profile pid-ctrl: 257 parameters"  # the table's 256 entries too


@pytest.mark.parametrize("name", docgen.SCHEMAS)
def test_every_key_example_is_valid_for_its_key(name: str) -> None:
    root = schema.schema(name)
    checked = 0
    for at, node in docgen.schema_nodes(root):
        if "examples" in node and at != "#":
            sub = {**{k: v for k, v in node.items() if k != "examples"}, "$defs": root.get("$defs", {})}
            for ex in node["examples"]:
                errors = list(jsonschema.Draft202012Validator(sub).iter_errors(ex))
                assert not errors, (at, ex, errors[0].message)
                checked += 1
    assert checked >= (10 if name in ("profile", "recipe", "inventory") else 0)


@pytest.mark.parametrize("page", PAGES, ids=[str(p.relative_to(ROOT)) for p in PAGES])
def test_links_between_pages_resolve(page: Path) -> None:
    """Relative links point at files that exist, and at anchors the generated pages define."""
    for target in re.findall(r"\]\(([^)\s]+)\)", page.read_text()):
        if re.match(r"[a-z]+:", target):
            continue
        path, _, frag = target.partition("#")
        dest = (page.parent / path).resolve() if path else page
        assert dest.exists(), (page.name, target)
        if frag and dest.suffix == ".md" and "reference" in dest.parts:
            assert f'id="{frag}"' in dest.read_text(), (page.name, target)


def test_every_page_is_in_the_site_navigation() -> None:
    """mkdocs.yml's nav lists every page of docs/ (mkdocs build --strict refuses a page left out)."""
    nav = yaml.safe_load((ROOT / "mkdocs.yml").read_text())["nav"]

    def pages(entries: list[object]) -> set[str]:
        found: set[str] = set()
        for entry in entries:
            for value in entry.values() if isinstance(entry, dict) else [entry]:
                found |= pages(value) if isinstance(value, list) else {str(value)}
        return found

    on_disk = {p.relative_to(DOCS).as_posix() for p in DOCS.rglob("*.md")}
    assert sorted(on_disk - pages(nav)) == [], "add these pages to the nav in mkdocs.yml"
    assert sorted(pages(nav) - on_disk) == []


# options a page describes before they exist on the commands (none now)
NOT_YET: set[str] = set()


def _command_lines(text: str) -> list[str]:
    """`deployer ...` in code blocks (indented, optionally after `$ ` or `.venv/bin/`) and in code spans."""
    lines = re.findall(r"^(?: {4,}|\t)(?:\$ )?(?:\.venv/bin/)?(deployer [^\n#]*)", text, re.M)
    return lines + re.findall(r"`(?:\.venv/bin/)?(deployer [^`]+)`", text)


def test_every_command_and_option_in_the_docs_exists() -> None:
    """A renamed command or option fails here, not in a reader's shell."""
    import click

    from deployer.cli.base import cli as group

    ctx = click.Context(group)
    wrong = []
    for page in PAGES:
        for line in _command_lines(page.read_text()):
            cmd: click.Command = group
            for tok in line.split()[1:]:
                if isinstance(cmd, click.Group) and not tok.startswith("-"):
                    if tok.isupper() or "|" in tok:  # a placeholder (COMMAND) or alternatives
                        break
                    sub = cmd.get_command(ctx, tok)
                    if sub is None:
                        wrong.append(f"{page.name}: {line}: no command {tok!r}")
                        break
                    cmd = sub
                elif tok.startswith("--"):
                    name = tok.split("=")[0].rstrip(",;.)")
                    names = {o for p in cmd.params for o in (*p.opts, *p.secondary_opts)} | {"--help"}
                    if name not in names and name not in NOT_YET:
                        wrong.append(f"{page.name}: {line}: no option {name}")
    assert wrong == []
    assert sum(len(_command_lines(p.read_text())) for p in PAGES) > 100  # the pattern still finds them


def test_example_files_named_in_the_docs_exist() -> None:
    named = {m for p in PAGES for m in re.findall(r"\brecipes/examples/[\w.-]+\.yaml", p.read_text())}
    assert named and sorted(n for n in named if not (ROOT / n).exists()) == []


def test_the_layout_table_names_every_module() -> None:
    """docs/contributing.md's layout table: a row per folder naming each of its modules, a row per top module."""
    rows = dict(re.findall(r"^\| `(deployer/[^`]+)` \| (.*) \|$", (DOCS / "contributing.md").read_text(), re.M))
    package = ROOT / "deployer"
    missing = []
    for path in sorted(package.rglob("*.py")):
        rel = path.relative_to(ROOT)
        if path.name in ("__init__.py", "__main__.py"):
            continue
        if path.parent == package:
            if rel.as_posix() not in rows:
                missing.append(rel.as_posix())
            continue
        folder = f"{rel.parts[0]}/{rel.parts[1]}/"
        if f"`{path.stem}`" not in rows.get(folder, ""):
            missing.append(rel.as_posix())
    assert missing == [], "name these in the layout table of docs/contributing.md"


def test_every_dependency_says_why_it_is_there() -> None:
    """docs/dependencies.md has a row for every package pyproject.toml installs (the developer guide asks it)."""
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    wanted = [*project["dependencies"], *(d for extra in project["optional-dependencies"].values() for d in extra)]

    def norm(name: str) -> str:
        return re.sub(r"[-_.]+", "-", name).lower()

    named = {
        norm(n)
        for row in re.findall(r"^\| ([^|]+) \|", (DOCS / "dependencies.md").read_text(), re.M)
        for n in re.findall(r"[A-Za-z][\w.-]*", row.split("(")[0])
    }
    missing = sorted({norm(re.split(r"[\[<>=!~; ]", d)[0]) for d in wanted} - named)
    assert missing == [], "say why in docs/dependencies.md"


def test_the_readme_stays_a_front_page() -> None:
    """The detail goes into the manual; the README keeps a line and a link (and no tracker numbers)."""
    text = (ROOT / "README.md").read_text()
    assert len(text.splitlines()) <= 250, "move the detail into a page of docs/ and link it"
    assert re.findall(r"(?<![\w&/])#\d+\b", text) == []


def test_the_api_page_names_every_public_name() -> None:
    import deployer

    text = (DOCS / "api.md").read_text()
    assert sorted(n for n in deployer.__all__ if f"`{n}`" not in text) == [], "say what it is for in docs/api.md"
    code = "".join(re.findall(r"```python\n(.*?)```", text, re.S))
    compile(code, "api.md", "exec")
    assert sorted({n for n in re.findall(r"\bdeployer\.(\w+)", code)} - {*deployer.__all__, "aio"}) == []


def test_the_api_page_examples_run(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """Every python block of docs/api.md runs as written, in order, against simulators at the addresses it
    names (the example recipes beside it, as in a checkout)."""
    import shutil

    from deployer.profile import builtin_profile
    from deployer.testing.simulator import Simulator
    from tests.helpers import Simulators

    text = (DOCS / "api.md").read_text()
    blocks = re.findall(r"```python\n(.*?)```", text, re.S)
    addresses = sorted(set(re.findall(r"tcp://10\.0\.0\.\d+:502", text)))
    assert len(blocks) >= 5 and len(addresses) == 2
    shutil.copytree(ROOT / "recipes" / "examples", tmp_path / "recipes" / "examples")
    monkeypatch.chdir(tmp_path)
    with Simulators([Simulator(builtin_profile("example-inverter")) for _ in addresses]) as sims:
        for i, block in enumerate(blocks, 1):
            for address, sim in zip(addresses, sims, strict=True):
                block = block.replace(address, sim.url)
            exec(compile(block, f"docs/api.md, block {i}", "exec"), {"__name__": f"api_md_{i}"})
        import deployer

        line3 = deployer.load_recipe(tmp_path / "recipes" / "examples" / "conveyor-line3.yaml")
        assert deployer.diff(line3, sims[0].url) == [] and deployer.diff(line3, sims[1].url) != []  # rolled back
    out = capsys.readouterr().out
    assert "identity" in out and "{'F07': '10 s', 'stop_mode': 'coast'}" in out


def test_the_wine_gaps_on_the_windows_page_are_the_suites() -> None:
    """docs/windows.md's table of Wine's gaps is tests/conftest.py's WINE_GAPS, test for test and word for word."""
    from tests.conftest import WINE_GAPS

    text = (DOCS / "windows.md").read_text(encoding="utf-8")
    assert dict(re.findall(r"^\| `(test_\w+)` \| (.+) \|$", text, re.M)) == WINE_GAPS
