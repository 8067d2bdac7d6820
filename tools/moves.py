"""The layout moves of issue #18: modules moved (and split) with their code unchanged.

Two stages, each a mapping of old module -> new module(s):

- stage 1 (commit f931841, before: 6c8c7ad): the flat modules into subpackages; executor,
  planner and fleet split;
- stage 2: load/yamlsrc.py split into yamlsrc (the YAML builder), schema (JSON Schema checks
  with positions) and messages (clipping echoed values, closest names); recipe/loader.py split
  into loader and text (recipe text that loads back to given registers).

``python tools/moves.py apply --stage N`` performs a stage on a tree that has the layout before
it; ``python tools/moves.py check --stage N OLD_REV`` proves it afterwards: every top-level
definition of every old module is found, with an identical syntax tree, in exactly one new
module, every other module (tests, benchmarks and the collection too in stage 2) is unchanged
but for import statements, and a name reached through a split module (``yamlsrc.schema``) is
now reached through the module that holds it (``schema.schema``). Stage 1 is the default.
"""

from __future__ import annotations

import ast
import copy
import os
import subprocess
import sys
from collections import defaultdict

PKG = "deployer"

# old module -> new module (moved whole) or {new module: [names]} (split; unnamed names stay in the first)
STAGE1: dict[str, str | dict[str, list[str]]] = {
    "yamlsrc": "load.yamlsrc",
    "diagnostics": "load.diagnostics",
    "codec": "profile.codec",
    "units": "profile.units",
    "skeleton": "profile.skeleton",
    "profile.csv_import": "profile.importers.spreadsheet",
    "profile.sunspec": "profile.importers.sunspec",
    "recipe": "recipe.loader",
    "frames": "planning.frames",
    "urls": "transport.urls",
    "transport": "transport.clients",
    "durable": "state.durable",
    "journal": "state.journal",
    "lock": "state.lock",
    "snapshot": "state.snapshot",
    "simulator": "testing.simulator",
    "progress": "cli.progress",
    "tables": "cli.tables",
    "docgen": "cli.docgen",
    "demo": "cli.demo",
    "planner": {
        "planning.planner": ["_REQUEST", "_plan_run", "merge_fields", "plan_writes", "plan_reads", "gap_free_reads",
                         "make_plan"],
        "planning.model": ["PLAN_SCHEMA", "Action", "Target", "PlannedParameter", "WriteRequest", "ReadRequest", "Plan"],
        "planning.planfile": ["plan_to_json", "plan_from_json", "load_plan"],
        "planning.wire": ["BAUD", "CHAR_BITS", "_rtu_request_bytes", "_rtu_response_bytes", "line_cost", "wire_stats"],
    },
    "executor": {
        "execute.device": ["_results", "_Shared", "_SHARED", "_SHARED_KEPT", "_shared", "apply_device",
                           "_apply_device", "_broadcast", "_apply", "_write_verify_commit", "_write_all"],
        "execute.session": ["Confirm", "StalePlan", "Declined", "ApplyOptions", "DeviceGone", "Session", "_none"],
        "execute.steps": ["check_identity", "check_preconditions", "_send_actions"],
        "execute.verify": ["values_of", "_values", "PENDING", "_attempted", "_verify"],
        "execute.recovery": ["_remerge", "_recover"],
        "execute.read": ["read_current"],
        "fleet.rollout": ["Job", "ReadJob", "_HasBus", "_J", "on_buses", "skipped_result", "Budget", "apply_many",
                          "batch_failed", "read_many"],
    },
    "fleet": {
        "fleet.inventory": ["FleetDevice", "Inventory", "select", "not_ok", "load_inventory", "_overrides_key",
                            "RecipeCache", "fleet_jobs"],
        "fleet.rollout": ["_count", "batch_sizes", "failure_budget"],
        "fleet.livereport": ["NOT_FINISHED", "not_finished", "_device_json", "_report_parts", "report_text",
                             "LiveReport"],
    },
}

DOCS = {
    "load": "Loading input files: safe YAML with positions, schema checks, diagnostics.",
    "profile.importers": "Profile importers: vendor register tables (CSV, xlsx) and SunSpec models.",
    "recipe": "Recipes: loading, validation against a profile, and recipe text.",
    "planning": "Planning: the plan model, the planner, the plan file and the wire cost.",
    "transport": "Transports: device URLs and the clients behind them, chosen by URL scheme.",
    "execute": "Executing a plan on one device: the session, the steps, writes, recovery and read-back.",
    "fleet": "Fleets: inventories, the rollout over many devices, and the live report file.",
    "state": "State kept between runs: durable writes, the journal, device locks and snapshots.",
    "testing": "Test doubles for users of deployer: the simulated Modbus device.",
}

ALLOWED1 = {("load.yamlsrc", "schema")}  # the schemas folder is now one level up

STAGE2: dict[str, str | dict[str, list[str]]] = {
    "load.yamlsrc": {
        "load.yamlsrc": [],  # unnamed definitions stay here: the builder, Source, read_text, load
        "load.schema": ["_is_number", "_is_integer", "schema", "validator", "_fast_validator", "is_valid",
                        "validate", "_leaves", "_where", "_explain", "_clip_message", "_type_words", "_describe"],
        "load.messages": ["MAX_ECHO", "clip", "clipped_repr", "_LONG_WORD", "clip_message", "closest"],
    },
    "recipe.loader": {
        "recipe.loader": [],
        "recipe.text": ["_range_text", "value_text", "_PLAIN_SAFE", "_RESOLVER", "_reads_back", "snapshot_value", "recipe_text",
                        "_body_line", "_PLAIN_KEY", "_key"],
    },
}

# patches the function where it now lives (a name in a string, which the rewrite cannot see)
ALLOWED2 = {("tests/test_docs.py", "test_undescribed_finds_a_missing_description")}

STAGES = {"1": (STAGE1, ALLOWED1), "2": (STAGE2, ALLOWED2)}
MOVES, ALLOWED = STAGES["1"]


def use(stage: str) -> None:
    global MOVES, ALLOWED
    MOVES, ALLOWED = STAGES[stage]


class _NoImports(ast.NodeTransformer):
    """Imports inside a definition are compared by the names they bind, not by where they point."""

    def __init__(self) -> None:
        self.bound: list[str] = []

    def generic_visit(self, node: ast.AST) -> ast.AST:
        for field, value in ast.iter_fields(node):
            if isinstance(value, list) and value and isinstance(value[0], ast.stmt):
                kept = []
                for s in value:
                    if isinstance(s, ast.ImportFrom):
                        self.bound += [a.asname or a.name for a in s.names]
                    else:
                        kept.append(self.visit(s))
                self.bound = sorted(set(self.bound))
                setattr(node, field, kept)
            elif isinstance(value, ast.AST):
                self.visit(value)
            elif isinstance(value, list):
                for v in value:
                    if isinstance(v, ast.AST):
                        self.visit(v)
        return node


def fingerprint(stmt: ast.stmt) -> str:
    t = _NoImports()
    node = t.visit(copy.deepcopy(stmt))
    return ast.dump(node) + repr(sorted(t.bound))


def path_of(mod: str, root: str = PKG) -> str:
    p = os.path.join(root, *mod.split("."))
    return os.path.join(p, "__init__.py") if os.path.isdir(p) else p + ".py"


def split_map() -> dict[tuple[str, str], str]:
    out: dict[tuple[str, str], str] = {}
    for old, new in MOVES.items():
        if isinstance(new, dict):
            for mod, names in new.items():
                for n in names:
                    out[(old, n)] = mod
    return out


def top_names(node: ast.stmt) -> list[str]:
    if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
        return [node.name]
    if isinstance(node, ast.Assign):
        return [n.id for t in node.targets for n in ([t] if isinstance(t, ast.Name) else getattr(t, "elts", []))
                if isinstance(n, ast.Name)]
    if isinstance(node, (ast.AnnAssign, ast.AugAssign)) and isinstance(node.target, ast.Name):
        return [node.target.id]
    return []


def resolve(current: str, is_pkg: bool, level: int, module: str | None) -> str:
    """The absolute dotted name (without 'deployer.') a relative import means."""
    parts = current.split(".") if current else []
    base = parts if is_pkg else parts[:-1]
    if level > 1:
        base = base[: len(base) - (level - 1)]
    return ".".join(base + ([module] if module else []))


def relative(current: str, is_pkg: bool, target: str) -> tuple[int, str]:
    cur = current.split(".") if current else []
    here = cur if is_pkg else cur[:-1]
    tgt = target.split(".")
    common = 0
    while common < len(here) and common < len(tgt) - 1 and here[common] == tgt[common]:
        common += 1
    level = len(here) - common + 1
    return level, ".".join(tgt[common:])


def new_module(old: str) -> str:
    m = MOVES.get(old)
    if isinstance(m, str):
        return m
    return old


def rewrite_imports(text: str, current: str, is_pkg: bool, absolute: bool, smap: dict[tuple[str, str], str],
                    current_is_old: bool = True, origin: str | None = None) -> str:
    """Rewrite every deployer import in text for the new layout. current: the module's new name."""
    tree = ast.parse(text)
    lines = text.splitlines(keepends=True)
    edits: list[tuple[int, int, int, int, str]] = []
    where = origin if origin is not None else current
    for node in ast.walk(tree):
        if not isinstance(node, ast.ImportFrom):
            continue
        if absolute:
            if not (node.module == PKG or (node.module or "").startswith(PKG + ".")) or node.level:
                continue
            target = (node.module or "")[len(PKG) + 1:]
        else:
            if not node.level:
                continue
            target = resolve(where, is_pkg, node.level, node.module)
        groups: dict[str, list[str]] = defaultdict(list)
        for alias in node.names:
            text_alias = alias.name + (f" as {alias.asname}" if alias.asname else "")
            sub = f"{target}.{alias.name}" if target else alias.name
            if sub in MOVES or os.path.exists(path_of(sub)) or sub in {new_module(k) for k in MOVES}:
                # a module imported by name
                nm = new_module(sub) if sub in MOVES else sub
                if isinstance(MOVES.get(sub), dict):
                    print(f"{where or 'absolute'}: module import of split module {sub}: fix by hand")
                    groups[target].append(text_alias)
                    continue
                parent, _, leaf = nm.rpartition(".")
                alias_txt = f" as {alias.asname}" if alias.asname else ""
                if leaf != alias.name and not alias.asname:
                    alias_txt = f" as {alias.name}"
                if absolute:
                    groups["@" + PKG + ("." + parent if parent else "")].append(leaf + alias_txt)
                else:
                    lvl, rest = relative(current, is_pkg, nm)
                    rest = rest.rpartition(".")[0]
                    groups["@" + "." * lvl + rest].append(leaf + alias_txt)
            elif (target, alias.name) in smap:
                groups[smap[(target, alias.name)]].append(text_alias)
            else:
                groups[new_module(target)].append(text_alias)
        stmts = []
        for mod, names in groups.items():
            if mod.startswith("@"):
                src_mod = mod[1:]
            elif absolute:
                src_mod = PKG + ("." + mod if mod else "")
            else:
                if mod == "":
                    lvl = len((current.split(".") if is_pkg else current.split(".")[:-1])) + 1
                    src_mod = "." * lvl
                else:
                    lvl, rest = relative(current, is_pkg, mod)
                    src_mod = "." * lvl + rest
            stmts.append(f"from {src_mod} import {', '.join(names)}")
        indent = " " * node.col_offset
        new = ("\n" + indent).join(stmts)
        edits.append((node.lineno, node.col_offset, node.end_lineno or node.lineno, node.end_col_offset or 0, new))
    for l1, c1, l2, c2, new in sorted(edits, reverse=True):
        start = sum(len(x) for x in lines[: l1 - 1]) + c1
        end = sum(len(x) for x in lines[: l2 - 1]) + c2
        text = text[:start] + new + text[end:]
        lines = text.splitlines(keepends=True)
    return text


def chunks(text: str) -> tuple[str, list[str], list[tuple[list[str], str]]]:
    """(docstring, import statements, [(names, source incl. leading comments)])."""
    tree = ast.parse(text)
    lines = text.splitlines(keepends=True)
    doc = ""
    imports: list[str] = []
    out: list[tuple[list[str], str]] = []
    prev_end = 0
    for i, node in enumerate(tree.body):
        start = prev_end
        seg = "".join(lines[start: node.end_lineno])
        prev_end = node.end_lineno or prev_end
        if i == 0 and isinstance(node, ast.Expr) and isinstance(node.value, ast.Constant):
            doc = seg
            continue
        if isinstance(node, (ast.Import, ast.ImportFrom)) or (
                isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test)):
            imports.append(seg.strip("\n") + "\n")
            continue
        names = top_names(node)
        if not names:
            raise SystemExit(f"unnamed top-level statement at line {node.lineno}")
        out.append((names, seg))
    return doc, imports, out


def git(*args: str) -> str:
    return subprocess.run(["git", *args], check=True, capture_output=True, text=True).stdout


def ensure_pkg(mod: str) -> None:
    parts = mod.split(".")[:-1]
    for i in range(1, len(parts) + 1):
        d = os.path.join(PKG, *parts[:i])
        os.makedirs(d, exist_ok=True)
        init = os.path.join(d, "__init__.py")
        if not os.path.exists(init):
            key = ".".join(parts[:i])
            with open(init, "w") as f:
                f.write(f'"""{DOCS.get(key, key)}"""\n')


def apply() -> None:
    smap = split_map()
    all_files = [os.path.join(d, f) for d, _, fs in os.walk(PKG) for f in fs if f.endswith(".py")]
    old_text = {p: open(p).read() for p in all_files}

    def modname(p: str) -> tuple[str, bool]:
        rel = os.path.relpath(p, PKG)[:-3].replace(os.sep, ".")
        if rel.endswith("__init__"):
            return rel[: -len("__init__")].rstrip("."), True
        return rel, False

    results: dict[str, str] = {}
    parts: dict[str, tuple[str, str, str]] = {}
    removed: list[str] = []
    for p, text in old_text.items():
        old, is_pkg = modname(p)
        spec = MOVES.get(old)
        if spec is None:
            results[p] = rewrite_imports(text, old, is_pkg, False, smap)
        elif isinstance(spec, str):
            results[path_of_new(spec)] = rewrite_imports(text, spec, False, False, smap, origin=old)
            removed.append(p)
        else:
            doc, imports, body = chunks(text)
            owner = {n: m for m, ns in spec.items() for n in ns}
            per: dict[str, list[tuple[list[str], str]]] = defaultdict(list)
            first = next(iter(spec))
            for names, seg in body:
                per[owner.get(names[0], first)].append((names, seg))
            defined = {n: m for m, segs in per.items() for ns, _ in segs for n in ns}
            for mod, segs in per.items():
                code = "".join(s for _, s in segs)
                used = {x.id for x in ast.walk(ast.parse(code)) if isinstance(x, ast.Name)}
                need: dict[str, list[str]] = defaultdict(list)
                for n in sorted(used):
                    if n in defined and defined[n] != mod:
                        need[defined[n]].append(n)
                head = doc if mod == first else f'"""{MOVES_DOC.get(mod, "")}"""\n'
                imp = "".join(imports)
                imp = rewrite_imports(imp, mod, False, False, smap, origin=old)
                code = rewrite_imports(code, mod, False, False, smap, origin=old)
                imp = drop_self_imports(imp, mod)
                extra = ""
                for m2, ns in need.items():
                    lvl, rest = relative(mod, False, m2)
                    extra += f"from {'.' * lvl}{rest} import {', '.join(ns)}\n"
                if "if TYPE_CHECKING:" in imp:
                    a, b = imp.split("if TYPE_CHECKING:", 1)
                    imp, extra = a + extra + "\nif TYPE_CHECKING:" + b, ""
                target = path_of_new(mod)
                h, i, c = parts.get(target, (head, "", ""))
                parts[target] = (h, i + imp + extra, c + ("\n\n" if c else "") + code)
            removed.append(p)
    for target, (h, i, c) in parts.items():
        results[target] = h + "\n" + i + c
    for p in removed:
        os.remove(p)
    for p, text in results.items():
        os.makedirs(os.path.dirname(p), exist_ok=True)
        rel = os.path.relpath(p, PKG)[:-3].replace(os.sep, ".")
        ensure_pkg(rel)
        with open(p, "w") as f:
            f.write(text)
    # empty old package dirs? none expected
    for root in ("tests", "benchmarks", "ansible_collections"):
        for d, _, fs in os.walk(root):
            for f in fs:
                if f.endswith(".py"):
                    fp = os.path.join(d, f)
                    t = open(fp).read()
                    t2 = rewrite_imports(t, "", False, True, smap)
                    if t2 != t:
                        with open(fp, "w") as fh:
                            fh.write(t2)


MOVES_DOC = {
    "planning.model": "The plan: a plain, serializable value (targets, planned parameters, write and read requests).",
    "planning.planfile": "Saved plans (`plan --out`): JSON to Plan and back, checked against the plan schema.",
    "planning.wire": "What a plan costs on the wire: RTU bytes and seconds at a line speed.",
    "execute.session": "One device's connection for a run: retries, the request log, options of an apply.",
    "execute.steps": "Steps around the writes: identity and precondition checks, unlock/commit/lock actions.",
    "execute.verify": "Register values of parameters, and verification of read-back values against the plan.",
    "execute.recovery": "What a refused or failed write request left on the device, found out by reading it.",
    "execute.read": "Reading a device's current values (plan, diff, pull, snapshots).",
    "fleet.inventory": "Inventories: devices, their selection (--limit) and the jobs a fleet run is made of.",
    "fleet.rollout": "The rollout over many devices: buses in parallel, batches, the failure budget.",
    "fleet.livereport": "The fleet report file, rewritten as devices finish (--limit @REPORT works after a crash).",
    "load.schema": "JSON Schema checks of loaded files, each error at the position of its key or value.",
    "load.messages": "Wording of input errors: values echoed cut to a readable length, the closest known name.",
    "recipe.text": "Recipe text written from register values (snapshots, pull) that loads back to the same registers.",
}


def drop_self_imports(imp: str, mod: str) -> str:
    """Imports of the module itself (a split put the name here) go, and TYPE_CHECKING blocks left empty."""
    leaf = mod.rpartition(".")[2]
    out = []
    for line in imp.splitlines(keepends=True):
        if line.strip().startswith(f"from .{leaf} import "):
            continue
        out.append(line)
    text = "".join(out)
    tree = ast.parse(text)
    for node in tree.body:
        if isinstance(node, ast.If) and all(
                isinstance(x, ast.ImportFrom) and not x.names for x in node.body) and not node.body:
            pass
    if text.rstrip().endswith("if TYPE_CHECKING:"):
        text = text.rstrip()[: -len("if TYPE_CHECKING:")] + "\n"
    return text


def path_of_new(mod: str) -> str:
    return os.path.join(PKG, *mod.split(".")) + ".py"


def split_targets() -> dict[str, str]:
    """Every module a split made or kept -> the old module it came from."""
    return {m: old for old, spec in MOVES.items() if isinstance(spec, dict) for m in spec}


def module_bindings(tree: ast.AST, current: str, is_pkg: bool, absolute: bool) -> dict[str, list[tuple[str, ast.ImportFrom]]]:
    """Names bound to a split module or one of its parts (old or new) -> (that module, the import)."""
    parts = split_targets()
    known = set(parts) | set(parts.values())
    out: dict[str, list[tuple[str, ast.ImportFrom]]] = defaultdict(list)
    for node in ast.walk(tree):
        if not isinstance(node, ast.ImportFrom):
            continue
        if node.level:
            if absolute:
                continue
            target = resolve(current, is_pkg, node.level, node.module)
        elif node.module == PKG or (node.module or "").startswith(PKG + "."):
            target = (node.module or "")[len(PKG) + 1:]
        else:
            continue
        for alias in node.names:
            sub = f"{target}.{alias.name}" if target else alias.name
            if sub in known:
                out[alias.asname or alias.name].append((sub, node))
    return out


def rewrite_attrs(text: str, current: str, is_pkg: bool, absolute: bool) -> str:
    """``yamlsrc.schema`` -> ``schema.schema`` where a split moved the name, with the import added."""
    smap = split_map()
    tree = ast.parse(text)
    bound = module_bindings(tree, current, is_pkg, absolute)
    taken = {n.id for n in ast.walk(tree) if isinstance(n, ast.Name)} | {
        a.arg for a in ast.walk(tree) if isinstance(a, ast.arg)}
    edits: list[tuple[int, int, int, str]] = []
    wanted: dict[int, dict[str, str]] = defaultdict(dict)  # id(import) -> {new module leaf: alias}
    imports: dict[int, ast.ImportFrom] = {}
    for node in ast.walk(tree):
        if not (isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name) and node.value.id in bound):
            continue
        # the import in force here: the last one above this line (imports are at the top of a scope)
        old, imp = max((b for b in bound[node.value.id] if b[1].lineno <= node.lineno),
                       key=lambda b: b[1].lineno, default=bound[node.value.id][0])
        spec = MOVES.get(old)
        if not isinstance(spec, dict):
            continue
        mod = smap.get((old, node.attr), next(iter(spec)))
        if mod == old:
            continue
        leaf = mod.rpartition(".")[2]
        alias = leaf if leaf not in taken else f"{node.value.id}_{leaf}"
        wanted[id(imp)][leaf] = alias
        imports[id(imp)] = imp
        v = node.value
        edits.append((v.lineno, v.col_offset, v.end_col_offset or 0, alias))
    lines = text.splitlines(keepends=True)
    for key, imp in imports.items():
        extra = ", ".join(leaf if a == leaf else f"{leaf} as {a}" for leaf, a in sorted(wanted[key].items()))
        line = imp.end_lineno or imp.lineno
        indent = " " * imp.col_offset
        edits.append((line, 10**9, 0, f"\n{indent}from {'.' * imp.level}{imp.module or ''} import {extra}"))
    for ln, c1, c2, new in sorted(edits, reverse=True):
        row = lines[ln - 1]
        if c1 == 10**9:
            body = row.rstrip("\n")
            lines[ln - 1] = body + new + row[len(body):]
        else:
            lines[ln - 1] = row[:c1] + new + row[c2:]
    return "".join(lines)


class _Canonical(ast.NodeTransformer):
    """Names bound to a split module or its parts, spelt as the old module (``@load.yamlsrc``)."""

    def __init__(self, bound: dict[str, list[tuple[str, ast.ImportFrom]]]) -> None:
        parts = split_targets()
        self.names = {b: "@" + parts.get(ms[0][0], ms[0][0]) for b, ms in bound.items()}

    def visit_Attribute(self, node: ast.Attribute) -> ast.AST:
        if isinstance(node.value, ast.Name) and node.value.id in self.names:
            node.value = ast.Name(id=self.names[node.value.id], ctx=node.value.ctx)
            return node
        return self.generic_visit(node)

    def visit_ImportFrom(self, node: ast.ImportFrom) -> ast.AST:
        names = {self.names.get(a.asname or a.name, a.asname or a.name) for a in node.names}
        return ast.ImportFrom(module="", names=[ast.alias(name=n) for n in sorted(names)], level=0)


def canonical(text: str, current: str, is_pkg: bool, absolute: bool) -> ast.Module:
    tree = ast.parse(text)
    return _Canonical(module_bindings(tree, current, is_pkg, absolute)).visit(tree)  # type: ignore[no-any-return]


def check(old_rev: str, outside: bool = False) -> int:
    """Compare old_rev's modules with the working tree's; outside: tests, benchmarks, collection too."""
    smap = split_map()
    roots = [PKG] + (["tests", "benchmarks", "ansible_collections", "tools"] if outside else [])
    files = [f for f in git("ls-tree", "-r", "--name-only", old_rev, *roots).split()
             if f.endswith(".py") and f != "tools/moves.py"]
    problems = 0
    compared = 0
    new_cache: dict[str, dict[str, str]] = {}

    def parsed(path: str, text: str) -> ast.Module:
        if not path.startswith(PKG + "/"):
            return canonical(text, "", False, True)
        rel = path[len(PKG) + 1:-3].replace("/", ".")
        is_pkg = rel.endswith("__init__")
        mod = rel[: -len("__init__")].rstrip(".") if is_pkg else rel
        return canonical(text, mod, is_pkg, False)

    def new_defs(mod: str) -> dict[str, str]:
        if mod not in new_cache:
            p = path_of(mod)
            tree = parsed(p, open(p).read())
            new_cache[mod] = {n: fingerprint(s) for s in tree.body for n in top_names(s)}
        return new_cache[mod]

    for f in files:
        tree = parsed(f, git("show", f"{old_rev}:{f}"))
        if not f.startswith(PKG + "/"):
            whole_old = [s for s in tree.body if not isinstance(s, ast.ImportFrom)]
            whole_new = [s for s in parsed(f, open(f).read()).body if not isinstance(s, ast.ImportFrom)]
            compared += 1
            same = len(whole_old) == len(whole_new) and all(
                fingerprint(a) == fingerprint(b) or any((f, n) in ALLOWED for n in top_names(a))
                for a, b in zip(whole_old, whole_new, strict=True))
            if not same:
                problems += 1
                print(f"DIFFERS: {f}")
            continue
        rel = f[len(PKG) + 1:-3].replace("/", ".")
        is_pkg = rel.endswith("__init__")
        old = rel[: -len(".__init__")] if is_pkg else rel
        if old == "__init__":
            old = ""
        if not isinstance(MOVES.get(old), dict):
            # moved whole (or not moved): the whole module, imports aside, is the same
            newp = path_of(new_module(old)) if old else path_of("__init__")
            whole_old = [s for s in tree.body if not isinstance(s, ast.ImportFrom)]
            whole_new = [s for s in parsed(newp, open(newp).read()).body if not isinstance(s, ast.ImportFrom)]
            same = [fingerprint(a) for a in whole_old] == [fingerprint(b) for b in whole_new]
            compared += 1
            if not same and not any(m == new_module(old) for m, _ in ALLOWED):
                problems += 1
                print(f"DIFFERS: module {old or PKG} -> {new_module(old)}")
        for stmt in tree.body:
            for n in top_names(stmt):
                spec = MOVES.get(old)
                if isinstance(spec, dict):
                    mod = smap.get((old, n), next(iter(spec)))
                else:
                    mod = new_module(old)
                got = new_defs(mod).get(n)
                compared += 1
                if got != fingerprint(stmt) and (mod, n) not in ALLOWED and (mod, "*") not in ALLOWED:
                    problems += 1
                    print(f"DIFFERS: {old}.{n} -> {mod}.{n}" + (" (missing)" if got is None else ""))
    print(f"{compared} top-level definitions and modules compared, {problems} differ "
          f"(allowed to differ: {sorted(ALLOWED)})")
    return 1 if problems else 0


def after_apply_stage2() -> None:
    """Names reached through a split module by attribute (``yamlsrc.schema``) now go to their module."""
    for root in (PKG, "tests", "benchmarks", "ansible_collections"):
        for d, _, fs in os.walk(root):
            for f in fs:
                if not f.endswith(".py"):
                    continue
                fp = os.path.join(d, f)
                text = open(fp).read()
                if root == PKG:
                    rel = os.path.relpath(fp, PKG)[:-3].replace(os.sep, ".")
                    is_pkg = rel.endswith("__init__")
                    mod = rel[: -len("__init__")].rstrip(".") if is_pkg else rel
                    new = rewrite_attrs(text, mod, is_pkg, False)
                else:
                    new = rewrite_attrs(text, "", False, True)
                if new != text:
                    with open(fp, "w") as fh:
                        fh.write(new)


if __name__ == "__main__":
    args = sys.argv[1:]
    stage = "1"
    if "--stage" in args:
        k = args.index("--stage")
        stage = args[k + 1]
        del args[k: k + 2]
    use(stage)
    if args[:1] == ["apply"]:
        apply()
        if stage == "2":
            after_apply_stage2()
    elif args[:1] == ["check"] and len(args) == 2:
        sys.exit(check(args[1], outside=stage != "1"))
    else:
        print(__doc__)
        sys.exit(2)
