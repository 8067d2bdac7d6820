"""Release metadata: one version everywhere, a changelog that has it, deprecations that say when."""

from __future__ import annotations

import re
import tomllib
from pathlib import Path

import yaml

import deployer

ROOT = Path(__file__).parent.parent
COLLECTION = ROOT / "ansible_collections" / "deployer" / "modbus"


def _version() -> str:
    return str(tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["version"])


def _major(version: str) -> int:
    return int(version.split(".")[0])


def test_one_version_everywhere() -> None:
    """pyproject.toml holds the version; the collection's galaxy.yml repeats it (Galaxy reads no other file)."""
    galaxy = yaml.safe_load((COLLECTION / "galaxy.yml").read_text())
    assert galaxy["version"] == _version(), "set galaxy.yml's version to pyproject.toml's"
    assert deployer.__version__ == _version(), "reinstall (pip install -e .): the installed metadata is stale"


def test_the_changelog_has_unreleased_and_this_version() -> None:
    text = (ROOT / "CHANGELOG.md").read_text()
    heads = re.findall(r"^## \[([^\]]+)\]", text, re.M)
    assert heads[0] == "Unreleased" and _version() in heads


def test_every_redirect_is_deprecated_with_a_removal_version() -> None:
    runtime = yaml.safe_load((COLLECTION / "meta" / "runtime.yml").read_text())
    routes = runtime["plugin_routing"]["modules"]
    assert routes, "no redirects: drop this test"
    for name, route in routes.items():
        removal = route["deprecation"]["removal_version"]
        # Ansible removes things in a major release of the collection, after the current one
        assert re.fullmatch(r"\d+\.0\.0", removal) and _major(removal) > _major(_version()), (name, removal)
        assert route["redirect"].split(".")[-1] in route["deprecation"]["warning_text"], name
