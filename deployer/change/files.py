"""Signed files: a plan's ``change`` and ``signatures`` members, and a recipe's or profile's detached
``FILE.signatures.json``."""

from __future__ import annotations

import hashlib
import json
import os
import socket
from collections.abc import Mapping
from typing import Any

from ..errors import Diagnostic, InputError, UsageError
from .canonical import SIGNATURES, bytes_digest, digest, utc_now

SIDECAR = ".signatures.json"
DETACHED = "deployer.signatures/1"
MAX_FILE = 64 << 20


def read_bounded(path: str, limit: int = MAX_FILE, what: str = "it") -> bytes:
    """A file's bytes, at most ``limit`` of them (InputError: unreadable or larger)."""
    try:
        with open(path, "rb") as f:
            data = f.read(limit + 1)
    except OSError as e:
        raise InputError([Diagnostic(path, 0, 0, f"cannot read {what}: {e.strerror}")]) from None
    if len(data) > limit:
        raise InputError([Diagnostic(path, 0, 0, f"{what} is larger than {limit >> 20} MiB")])
    return data


def is_plan(data: bytes) -> bool:
    """A saved plan or a saved fleet plan (both are signed and approved alike), by its first bytes."""
    return data.lstrip().startswith(b"{") and (
        b'"deployer.plan/' in data[:4096] or b'"deployer.fleetplan/' in data[:4096]
    )


def read_plan(path: str) -> dict[str, Any]:
    """A plan file as the JSON document it is (strict JSON: duplicate keys and NaN refused, as the digest needs)."""
    return parse_plan(read_bounded(path), path)


def parse_plan(data: bytes, path: str) -> dict[str, Any]:
    def pairs(items: list[tuple[str, Any]]) -> dict[str, Any]:
        keys = [k for k, _ in items]
        if len(set(keys)) != len(keys):
            raise ValueError(f"the key {next(k for k in keys if keys.count(k) > 1)!r} is given twice")
        return dict(items)

    def constant(name: str) -> Any:
        raise ValueError(f"{name} is not a JSON number")

    try:
        doc = json.loads(data.decode("utf-8"), object_pairs_hook=pairs, parse_constant=constant)
    except UnicodeDecodeError:
        raise InputError([Diagnostic(path, 0, 0, "a plan must be UTF-8 JSON")]) from None
    except json.JSONDecodeError as e:
        raise InputError([Diagnostic(path, e.lineno, e.colno, f"not JSON: {e.msg}")]) from None
    except ValueError as e:
        raise InputError([Diagnostic(path, 0, 0, f"not a plan: {e}")]) from None
    if not isinstance(doc, dict) or not str(doc.get("schema", "")).startswith(
        ("deployer.plan/", "deployer.fleetplan/")
    ):
        raise InputError([Diagnostic(path, 1, 1, "not a saved plan (deployer plan ... --out PLAN.json)")])
    return doc


def write_plan(path: str, doc: Mapping[str, Any]) -> None:
    """The plan written back whole or not at all, as ``plan --out`` writes it."""
    from ..state.durable import write_atomic

    write_atomic(path, json.dumps(doc, indent=2, ensure_ascii=False) + "\n", what="the plan")


def input_record(kind: str, path: str) -> dict[str, Any]:
    """A recipe or profile file the plan is made from: its path, its bytes' SHA-256, its detached signatures."""
    data = read_bounded(path)
    sigs = detached(path).get("signatures") or []
    return {"kind": kind, "path": path, "sha256": hashlib.sha256(data).hexdigest(), "signatures": sigs}


def change_member(
    author: str, *, reason: str | None, ticket: str | None, inputs: list[dict[str, Any]]
) -> dict[str, Any]:
    """The ``change`` member ``plan --out`` writes: who, when, where, why, which ticket, from which files."""
    out: dict[str, Any] = {"author": author, "time": utc_now(), "host": socket.gethostname()}
    if reason:
        out["reason"] = reason
    if ticket:
        out["ticket"] = ticket
    out["inputs"] = inputs
    return out


# ---- detached signatures ------------------------------------------------------------------------------


def sidecar(path: str) -> str:
    return path + SIDECAR


def detached(path: str) -> dict[str, Any]:
    """``FILE.signatures.json`` (an empty one when there is none; InputError when it is damaged)."""
    side = sidecar(path)
    if not os.path.exists(side):
        return {"schema": DETACHED, "file": os.path.basename(path), "signatures": []}
    try:
        doc = json.loads(read_bounded(side).decode("utf-8"))
    except (UnicodeDecodeError, ValueError) as e:
        raise InputError([Diagnostic(side, 0, 0, f"not a signatures file: {e}")]) from None
    if not isinstance(doc, dict) or doc.get("schema") != DETACHED or not isinstance(doc.get("signatures"), list):
        raise InputError([Diagnostic(side, 0, 0, f"not a {DETACHED} document")])
    return doc


class Signed:
    """A file as a signer sees it: its digest now and its signatures (a plan's own list, or detached)."""

    def __init__(self, path: str) -> None:
        self.path = path
        data = read_bounded(path)
        self.plan = parse_plan(data, path) if is_plan(data) else None
        self.digest = digest(self.plan) if self.plan is not None else bytes_digest(data)
        self.side = None if self.plan is not None else detached(path)

    @property
    def signatures(self) -> list[Any]:
        if self.plan is not None:
            sigs = self.plan.get(SIGNATURES)
            return list(sigs) if isinstance(sigs, list) else []
        assert self.side is not None
        return list(self.side["signatures"])

    def add(self, entry: Mapping[str, Any]) -> str:
        """Add a signature and write the file (the plan) or its sidecar; the path written."""
        from ..state.durable import write_atomic

        if self.plan is not None:
            sigs = self.plan.get(SIGNATURES)
            if sigs is not None and not isinstance(sigs, list):
                raise UsageError(f"{self.path}: its signatures member is not a list")
            self.plan[SIGNATURES] = [*(sigs or []), dict(entry)]
            write_plan(self.path, self.plan)
            return self.path
        assert self.side is not None
        self.side["signatures"] = [*self.side["signatures"], dict(entry)]
        write_atomic(
            sidecar(self.path), json.dumps(self.side, indent=2, ensure_ascii=False) + "\n", what="the signatures"
        )
        return sidecar(self.path)

    @property
    def author(self) -> str | None:
        change = (self.plan or {}).get("change")
        author = change.get("author") if isinstance(change, Mapping) else None
        return author if isinstance(author, str) else None
