"""The canonical JSON of a document and the digests made from it (docs/change-control.md)."""

from __future__ import annotations

import datetime
import hashlib
import json
from collections.abc import Mapping
from typing import Any

SIGNATURES = "signatures"  # the one top-level member outside a plan's digest


def canonical(value: Any) -> bytes:
    """Sorted keys, no spaces, UTF-8 without escapes, no NaN: the same document always gives the same bytes."""
    return json.dumps(value, sort_keys=True, separators=(",", ":"), ensure_ascii=False, allow_nan=False).encode()


def digest(doc: Mapping[str, Any]) -> str:
    """``sha256:HEX`` of the canonical JSON of ``doc`` without its top-level ``signatures``: signing a plan does
    not change it, changing anything else does (ValueError: a NaN or a value JSON cannot hold)."""
    return "sha256:" + hashlib.sha256(canonical({k: v for k, v in doc.items() if k != SIGNATURES})).hexdigest()


def bytes_digest(data: bytes) -> str:
    """``sha256:HEX`` of a file's bytes (a recipe or profile signed detached)."""
    return "sha256:" + hashlib.sha256(data).hexdigest()


def utc_now() -> str:
    """Now as ISO 8601 UTC to the second: ``2026-11-22T10:15:00Z``."""
    return datetime.datetime.now(datetime.UTC).strftime("%Y-%m-%dT%H:%M:%SZ")


def parse_time(text: str) -> datetime.datetime | None:
    """A signature's time (ISO 8601; UTC when it names no zone), or None when it is not one."""
    try:
        t = datetime.datetime.fromisoformat(text.replace("Z", "+00:00"))
    except (ValueError, AttributeError, TypeError):
        return None
    return t if t.tzinfo is not None else t.replace(tzinfo=datetime.UTC)
