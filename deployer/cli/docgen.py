"""Reference pages generated from the JSON Schemas, and `deployer explain KEY`.

The schemas carry every key's description, default, range and examples, so `validate` and the
docs cannot disagree: this module only walks them. A key added to a schema appears in the docs
after `deployer docs` (a test fails while the committed pages are stale).
"""

from __future__ import annotations

import json
import os
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field
from typing import Any

import yaml

from ..load import schema as schemas

SCHEMAS = ("profile", "recipe", "inventory", "plan", "fleetplan", "report", "users")
_NO_DEFAULT = object()


@dataclass(frozen=True)
class Key:
    """One key of a file format, as the reference shows it."""

    schema: str
    path: str  # "limits.max_frame_bytes", "parameters.NAME.scale", "identity[].raw"
    type: str
    required: bool
    description: str
    allowed: str = ""
    default: Any = _NO_DEFAULT
    examples: tuple[Any, ...] = ()
    same_as: str | None = None  # the key documenting this shape already (a $def met twice)

    @property
    def has_default(self) -> bool:
        return self.default is not _NO_DEFAULT


@dataclass
class _Walk:
    schema: str
    root: dict[str, Any]
    keys: list[Key] = field(default_factory=list)
    expanded: dict[str, str] = field(default_factory=dict)  # $def name -> path where it was documented
    seen: set[str] = field(default_factory=set)


def _deref(node: Mapping[str, Any], root: Mapping[str, Any]) -> tuple[dict[str, Any], str | None]:
    """The node with its $ref target merged in (the node's own keywords win), and the $def's name."""
    ref = node.get("$ref")
    if not isinstance(ref, str) or not ref.startswith("#/$defs/"):
        return dict(node), None
    name = ref.split("/")[-1]
    target, _ = _deref(root["$defs"][name], root)
    return {**target, **{k: v for k, v in node.items() if k != "$ref"}}, name


def _alternatives(
    node: Mapping[str, Any], root: Mapping[str, Any], depth: int = 0
) -> list[tuple[Mapping[str, Any], str | None]]:
    """The node and, recursively, its oneOf/anyOf/allOf alternatives, each with the $def it came from."""
    alts: list[tuple[Mapping[str, Any], str | None]] = [(node, None)]
    if depth > 4:
        return alts
    for kw in ("oneOf", "anyOf", "allOf"):
        for a in node.get(kw, []):
            d, name = _deref(a, root)
            alts += [(sub, sub_name or name) for sub, sub_name in _alternatives(d, root, depth + 1)]
    return alts


_WORDS = {
    "object": "mapping",
    "array": "list",
    "number": "number",
    "integer": "integer",
    "string": "string",
    "null": "null",
    "boolean": "boolean",
}


def type_text(node: Mapping[str, Any], root: Mapping[str, Any]) -> str:
    """A reader's word for the type: 'integer', 'list of string', 'number or string' ..."""
    if "const" in node:
        return "integer" if isinstance(node["const"], int) else "string"
    if "enum" in node:
        kinds = {"integer" if isinstance(v, int) else "string" for v in node["enum"]}
        return " or ".join(sorted(kinds))
    t = node.get("type")
    if isinstance(t, list):
        return " or ".join(_WORDS.get(str(x), str(x)) for x in t)
    if t == "array":
        items = node.get("items")
        return f"list of {type_text(_deref(items, root)[0], root)}" if isinstance(items, dict) else "list"
    if isinstance(t, str):
        return _WORDS.get(t, t)
    words: list[str] = []
    for kw in ("oneOf", "anyOf"):
        for alt in node.get(kw, []):
            for w in type_text(_deref(alt, root)[0], root).split(" or "):
                if w and w not in words:
                    words.append(w)
    if not words and node.get("allOf"):
        return type_text(_deref(node["allOf"][0], root)[0], root)
    return " or ".join(words)


def inline(value: Any) -> str:
    """A value as inline YAML (flow style), quoted only where YAML would read it differently."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if value is None:
        return "null"
    if isinstance(value, (int, float)):
        return json.dumps(value)
    if isinstance(value, str):
        plain = (
            value and not any(c in value for c in ",[]{}#&*!|>'\"%@`") and ": " not in value and value == value.strip()
        )
        try:
            plain = plain and yaml.safe_load(value) == value
        except yaml.YAMLError:
            plain = False
        return value if plain else json.dumps(value)
    if isinstance(value, list):
        return "[" + ", ".join(inline(v) for v in value) + "]"
    if isinstance(value, dict):
        return "{" + ", ".join(f"{inline(str(k))}: {inline(v)}" for k, v in value.items()) + "}"
    return json.dumps(value)


def allowed_text(node: Mapping[str, Any], root: Mapping[str, Any]) -> str:
    """Allowed values: enumerations, ranges, patterns, sizes; alternatives joined with '; '."""
    parts: list[str] = []
    if "enum" in node:
        parts.append(", ".join(f"`{inline(v)}`" for v in node["enum"]))
    if "const" in node:
        parts.append(f"`{inline(node['const'])}`")
    lo = node.get("minimum")
    hi = node.get("maximum")
    if lo is not None and hi is not None:
        parts.append(f"{lo}..{hi}")
    elif lo is not None:
        parts.append(f">= {lo}")
    elif hi is not None:
        parts.append(f"<= {hi}")
    if "exclusiveMinimum" in node:
        parts.append(f"> {node['exclusiveMinimum']}")
    if node.get("minLength") == 1:
        parts.append("not empty")
    if "pattern" in node:
        parts.append(f"matches `{node['pattern']}`")
    names = node.get("propertyNames", {})
    if "pattern" in names:
        parts.append(f"names match `{names['pattern']}`")
    if node.get("minProperties"):
        parts.append(f"at least {node['minProperties']} entr{'y' if node['minProperties'] == 1 else 'ies'}")
    if node.get("minItems"):
        parts.append(f"at least {node['minItems']} item{'' if node['minItems'] == 1 else 's'}")
    if node.get("maxItems"):
        parts.append(f"at most {node['maxItems']} items")
    items = node.get("items")
    if node.get("type") == "array" and isinstance(items, dict):
        inner = allowed_text(_deref(items, root)[0], root)
        if inner:
            parts.append(f"each {inner}")
    for kw in ("oneOf", "anyOf", "allOf"):
        for alt in node.get(kw, []):
            a = _deref(alt, root)[0]
            if a.get("type") in ("object", "null") or "properties" in a:
                continue  # mapping forms are documented by their own keys
            text = allowed_text(a, root)
            if text and text not in parts:
                parts.append(text)
    return "; ".join(parts)


_PLACEHOLDERS = {
    "parameters": "PARAM",
    "values": "LABEL",
    "fields": "FIELD",
    "tables": "TABLE",
    "devices": "DEVICE",
    "registers": "PARAM",
}


def _placeholder(path: str) -> str:
    """The stand-in for a user-chosen key: parameters.PARAM, tables.TABLE.fields.FIELD ..."""
    last = path.rsplit(".", 1)[-1]
    if last in _PLACEHOLDERS:
        return _PLACEHOLDERS[last]
    return "FIELD" if last.isupper() else "NAME"  # a table entry's fields in a recipe: parameters.PARAM.FIELD


def _join(path: str, name: str) -> str:
    return f"{path}.{name}" if path else name


def _shaped(node: Mapping[str, Any], root: Mapping[str, Any]) -> bool:
    """Whether a schema has keys of its own to document (a mapping or a list of mappings)."""
    for alt, _ in _alternatives(node, root):
        items = alt.get("items")
        if (
            "properties" in alt
            or isinstance(alt.get("additionalProperties"), dict)
            or (isinstance(items, dict) and "properties" in _deref(items, root)[0])
        ):
            return True
    return False


def _walk(w: _Walk, raw: Mapping[str, Any], path: str, required: bool) -> None:
    node, def_name = _deref(raw, w.root)
    shaped = bool(def_name) and _shaped(node, w.root)
    if path:
        same_as = w.expanded.get(def_name) if def_name and shaped else None
        if path not in w.seen:
            w.seen.add(path)
            w.keys.append(
                Key(
                    w.schema,
                    path,
                    type_text(node, w.root),
                    required,
                    str(node.get("description", "")).strip(),
                    allowed_text(node, w.root),
                    node.get("default", _NO_DEFAULT),
                    tuple(node.get("examples", ())),
                    same_as,
                )
            )
        if same_as is not None:
            return
    if def_name and shaped:
        w.expanded[def_name] = path
    for alt, alt_def in _alternatives(node, w.root):
        if alt_def is not None and alt_def != def_name:
            if w.expanded.get(alt_def, path) != path:
                continue  # documented at another key already
            w.expanded[alt_def] = path
        req = set(alt.get("required", [])) if alt is node else set()
        for name, sub in alt.get("properties", {}).items():
            _walk(w, sub, _join(path, name), name in req)
        extra = alt.get("additionalProperties")
        if isinstance(extra, dict):
            _walk(w, extra, _join(path, _placeholder(path)), False)
        items = alt.get("items")
        if isinstance(items, dict) and alt is node:
            item, _ = _deref(items, w.root)
            if "properties" in item:
                _walk_children(w, item, f"{path}[]")


def _walk_children(w: _Walk, node: Mapping[str, Any], path: str) -> None:
    req = set(node.get("required", []))
    for name, sub in node.get("properties", {}).items():
        _walk(w, sub, _join(path, name), name in req)


def schema_keys(name: str) -> list[Key]:
    """Every key of one schema, in document order (parents before their children)."""
    w = _Walk(name, schemas.schema(name))
    _walk(w, w.root, "", True)
    return w.keys


def all_keys() -> Iterator[Key]:
    for name in SCHEMAS:
        yield from schema_keys(name)


def schema_nodes(node: Any, at: str = "#") -> Iterator[tuple[str, dict[str, Any]]]:
    """Every mapping in a schema with its JSON pointer, parents first."""
    if isinstance(node, dict):
        yield at, node
        for key, sub in node.items():
            yield from schema_nodes(sub, f"{at}/{key}")
    elif isinstance(node, list):
        for i, sub in enumerate(node):
            yield from schema_nodes(sub, f"{at}/{i}")


def undescribed(name: str) -> list[str]:
    """JSON pointers of properties and $defs without a description (a test requires none)."""
    root = schemas.schema(name)
    missing: list[str] = []
    for at, node in schema_nodes(root):
        for key, sub in (node.get("properties") or {}).items():
            if not isinstance(sub, dict) or not str(sub.get("description", "")).strip():
                missing.append(f"{at}/properties/{key}")
        extra = node.get("additionalProperties")  # a user-named key (parameters.PARAM): documented too
        if isinstance(extra, dict) and not str(_deref(extra, root)[0].get("description", "")).strip():
            missing.append(f"{at}/additionalProperties")
    for key, sub in (root.get("$defs") or {}).items():
        if not str(sub.get("description", "")).strip():
            missing.append(f"#/$defs/{key}")
    if not str(root.get("description", "")).strip():
        missing.append("#")
    return missing


# ---- rendering ------------------------------------------------------------------------------

TITLES = {
    "profile": "Profile files",
    "recipe": "Recipe files",
    "inventory": "Inventory files",
    "plan": "Saved plans (PLAN.json)",
    "fleetplan": "Saved fleet plans (FLEET.json)",
    "report": "Reports (REPORT.json)",
    "snapshot": "Snapshots",
    "users": "The agent's users file",
}
_JSON = {"plan", "fleetplan", "report"}
_HEADER = (
    "<!-- Generated by `deployer docs` from deployer/schemas/{name}.schema.json: edit the schema, "
    "then run `make docs`. -->\n"
)


def _cell(text: str) -> str:
    return text.replace("|", "\\|").replace("\n", " ")


def _example_text(key: Key, value: Any) -> str:
    last = key.path.rsplit(".", 1)[-1]
    if last.isupper() or "[]" in last:
        return f"`{inline(value)}`"
    return f"`{last}: {inline(value)}`"


def anchor(path: str) -> str:
    """An HTML id for a key path (no brackets or dots, which trip Markdown link parsers)."""
    return path.replace("[]", "-items").replace(".", "-").lower()


def render_text(key: Key, width: int = 88) -> str:
    """One key for the terminal (`deployer explain`)."""
    import textwrap

    facts = [("required" if key.required else "optional"), key.type]
    if key.has_default:
        facts.append(f"default {inline(key.default)}")
    if key.allowed:
        facts.append(f"allowed: {key.allowed}")
    out = [f"{key.schema}: {key.path}"]
    for para in (
        " · ".join(facts),
        key.description,
        f"Same keys as {key.same_as}." if key.same_as else "",
        ("Example: " + ", ".join(_example_text(key, v).strip("`") for v in key.examples)) if key.examples else "",
    ):
        if para:
            out += textwrap.wrap(para.replace("`", ""), width, initial_indent="  ", subsequent_indent="  ")
    return "\n".join(out)


def render_key(key: Key, *, heading: str = "###") -> str:
    """One key's section: type, required/default, allowed values, meaning, examples."""
    facts = [("required" if key.required else "optional"), key.type]
    if key.has_default:
        facts.append(f"default `{inline(key.default)}`")
    if key.allowed:
        facts.append(f"allowed: {key.allowed}")
    lines = [f'<a id="{anchor(key.path)}"></a>', f"{heading} `{key.path}`", "", " · ".join(f for f in facts if f), ""]
    if key.description:
        lines += [key.description, ""]
    if key.same_as:
        lines += [f"Same keys as [`{key.same_as}`](#{anchor(key.same_as)}).", ""]
    if key.examples:
        label = "Example" if len(key.examples) == 1 else "Examples"
        lines += [f"{label}: " + ", ".join(_example_text(key, v) for v in key.examples), ""]
    return "\n".join(lines)


def compact_json(value: Any, indent: str = "") -> str:
    """JSON with small mappings and lists of numbers on one line: readable examples."""
    flat = json.dumps(value)
    if len(flat) + len(indent) <= 100 or not isinstance(value, (dict, list)):
        return flat
    inner = indent + "  "
    if isinstance(value, dict):
        body = [f"{inner}{json.dumps(k)}: {compact_json(v, inner)}" for k, v in value.items()]
        return "{\n" + ",\n".join(body) + f"\n{indent}}}"
    return "[\n" + ",\n".join(inner + compact_json(v, inner) for v in value) + f"\n{indent}]"


def compact_yaml(value: Any, indent: int = 0) -> str:
    """Block-style YAML whose small mappings and lists stay on one line, as people write profiles."""
    pad = " " * indent
    lines: list[str] = []
    items = value.items() if isinstance(value, dict) else enumerate(value)
    for k, v in items:
        head = f"{pad}{inline(str(k))}:" if isinstance(value, dict) else f"{pad}-"
        flat = inline(v)
        nested = isinstance(v, (dict, list)) and any(
            isinstance(x, (dict, list)) for x in (v.values() if isinstance(v, dict) else v)
        )
        if not isinstance(v, (dict, list)) or (not nested and len(head) + len(flat) < 100) or not v:
            lines.append(f"{head} {flat}")
        elif isinstance(value, list) and isinstance(v, dict):
            body = compact_yaml(v, indent + 2).splitlines()
            lines += [f"{head} {body[0].lstrip()}", *body[1:]]
        else:
            lines += [head, compact_yaml(v, indent + 2).rstrip("\n")]
    return "\n".join(lines) + "\n"


def _example_block(name: str, value: Any) -> str:
    if name in _JSON:
        return "```json\n" + compact_json(value) + "\n```\n"
    return "```yaml\n" + compact_yaml(value) + "```\n"


def _names_files(value: Any) -> bool:
    """Whether an example's ``recipe`` or ``profile`` names a file (``recipes/zone.yaml``) that is not part of it."""
    if isinstance(value, dict):
        return any(
            (k in ("recipe", "profile") and isinstance(v, str) and v.endswith((".yaml", ".yml", ".json")))
            or _names_files(v)
            for k, v in value.items()
        )
    return isinstance(value, list) and any(_names_files(v) for v in value)


def render_page(name: str) -> str:
    """The reference page of one schema (Markdown)."""
    root = schemas.schema(name)
    keys = schema_keys(name)
    out = [
        _HEADER.format(name=name),
        f"# {TITLES[name]}",
        "",
        str(root.get("description", "")).strip(),
        "",
        f"Schema: `deployer/schemas/{name}.schema.json` (draft 2020-12). `deployer explain KEY` prints any "
        "key's entry below on the command line.",
        "",
    ]
    for i, ex in enumerate(root.get("examples", [])):
        out += ["## Example" + (f" {i + 1}" if len(root["examples"]) > 1 else ""), ""]
        if name == "inventory" and _names_files(ex):  # names the reader's files: not checkable on its own
            out += ["<!-- example: partial -->"]
        out += [_example_block(name, ex)]
    out += ["## Keys", "", "| key | type | required | default |", "|---|---|---|---|"]
    for k in keys:
        default = f"`{_cell(inline(k.default))}`" if k.has_default else ""
        out.append(f"| [`{k.path}`](#{anchor(k.path)}) | {_cell(k.type)} | {'yes' if k.required else ''} | {default} |")
    out.append("")
    for k in keys:
        out.append(render_key(k))
    return "\n".join(out).rstrip() + "\n"


SNAPSHOT_INTRO = """\
Before its first write to a device, `apply` saves what the device held as a **snapshot** under
`STATE/snapshots/NAME-YYYYMMDDTHHMMSSZ.yaml` (`STATE` is `--state-dir`, default `.deployer`),
durable before that write: its text in a write-ahead log, the file fsync'ed when the run ends, and restored
from the log after a crash ([applying](../applying.md#snapshots-are-durable-before-the-first-write)).
Its absolute path is in the report (`snapshot`) and the journal.

A snapshot **is a recipe** ([recipe reference](recipe.md)), checked by the same schema, so
`validate`, `plan`, `diff` and `apply` take it like any recipe; `deployer rollback SNAPSHOT`
applies it. What makes it self-contained:

- `profile` names the profile unambiguously: a built-in id or the file's absolute path;
- `device` is the device it was read from (URL without certificate paths, and unit); the URL keeps what it
  takes to talk to the device as the apply did: its `timeout` and `retries` where they were not the
  defaults (from the URL or the inventory), its pauses and `device_identification` as the URL gave them
  (`rollback --timeout`/`--retries` go over the recorded ones);
- the `snapshot` block ([`snapshot`](recipe.md#snapshot) in the recipe reference) records
  `profile_sha256` (the profile's text then), `taken`, `applied` (the recipe written after it)
  and `registers`: every parameter's raw words as the device held them;
- `parameters` says the same values in engineering units; a value outside the profile's range
  (factory values often are) appears as `{raw: N}` with a comment.

`rollback` writes the recorded raw registers back exactly, to the device the snapshot came
from, from any working directory: the profile's range does not block a value the device itself
held. Before anything is sent it refuses a snapshot whose profile changed (the SHA-256 differs;
`--force` restores the raw registers anyway), whose `parameters` disagree with `registers` (an
edited file), or that is pointed at a fleet; another `--device` or `--unit` asks first.

A snapshot holds the parameters of the applied recipe that could be read, at their values before
the apply; parameters the recipe did not name are not in it (apply never wrote them).
"""


def render_snapshot_page() -> str:
    """The snapshot page; its example is written by the code that writes snapshots (recipe_text)."""
    import calendar
    import time

    from ..api.commands import snapshot_text

    before = {"F07": (0, 500), "F08": (0, 500), "stop_mode": (0,), "base_speed": (0x6590,)}
    stamp, applied = "20261122T101500Z", "/plant/recipes/conveyor-line3.yaml"
    text = snapshot_text(
        "example-inverter",
        before,
        name="press-1",
        url="tcp://10.0.0.11:502",
        unit=1,
        applied=applied,
        path=f"/plant/.deployer/snapshots/press-1-{stamp}.yaml",
        taken=calendar.timegm(time.strptime(stamp, "%Y%m%dT%H%M%SZ")),
    )
    return "\n".join(
        [
            "<!-- Generated by `deployer docs` (deployer/docgen.py): the example is written by the code that "
            "writes snapshots. -->\n",
            f"# {TITLES['snapshot']}",
            "",
            SNAPSHOT_INTRO,
            "## Example",
            "",
            "```yaml",
            text.rstrip(),
            "```",
            "",
        ]
    )


def pages() -> dict[str, str]:
    """File name -> content of every generated reference page."""
    out = {f"{name}.md": render_page(name) for name in SCHEMAS}
    out["snapshot.md"] = render_snapshot_page()
    return out


def _on_disk(path: str) -> str | None:
    try:
        with open(path, encoding="utf-8") as f:
            return f.read()
    except OSError:
        return None


GENERATED = "<!-- Generated by `deployer docs`"  # how every page begins: such a file is ours to rewrite


def write_pages(directory: str, *, force: bool = False) -> list[str]:
    """Write the pages; returns the files whose content changed.

    A page there already is rewritten when it is one of ours (it begins with GENERATED); any other
    file of that name only with ``force`` (OutputRefused otherwise, before anything is written).
    """
    from ..api.commands import check_output
    from ..api.commands import write_output as write_atomic

    os.makedirs(directory, exist_ok=True)
    todo = []
    for fname, text in pages().items():
        path = os.path.join(directory, fname)
        now = _on_disk(path) if os.path.isfile(path) and not os.path.islink(path) else None
        if now == text:
            continue
        check_output(path, replace=force or (now is not None and now.startswith(GENERATED)), what="the page")
        todo.append((path, text))
    for path, text in todo:
        write_atomic(path, text, replace=True, what="the page")
    return [path for path, _ in todo]


def stale_pages(directory: str) -> list[str]:
    """Pages in ``directory`` that differ from what the schemas generate now (or are missing)."""
    return [
        os.path.join(directory, fname)
        for fname, text in pages().items()
        if _on_disk(os.path.join(directory, fname)) != text
    ]


def url_option_text(name: str) -> str | None:
    """A device URL option for the terminal (`deployer explain baudrate`); None if no scheme takes it."""
    from ..api.commands import url_option

    schemes, default, allowed = url_option(name)
    if not schemes:
        return None
    facts = (
        [f"device URL option ({', '.join(schemes)})"]
        + ([f"default {default}"] if default else [])
        + ([f"allowed: {allowed}"] if allowed else [])
    )
    return f"url: {name}\n  " + " · ".join(facts) + "\n  Every scheme and option, with what they mean: docs/urls.md"


def find_keys(query: str) -> list[Key]:
    """Keys matching ``query``: a full path (``limits.max_frame_bytes``), its tail (``max_frame_bytes``),
    optionally prefixed by the file kind (``profile:scale``)."""
    kind, _, q = query.rpartition(":")
    q = q.strip().strip(".")
    found = []
    for k in all_keys():
        if kind and k.schema != kind:
            continue
        if k.path == q or k.path.endswith("." + q) or k.path.endswith("[]." + q):
            found.append(k)
    return found
