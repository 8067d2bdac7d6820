"""YAML (and JSON) loading that remembers where every key and value came from.

We build plain Python values from PyYAML's event stream ourselves so that:
  * only safe, standard tags are accepted (no Python object tags),
  * decimal numbers become ``Decimal`` built from the text (``10.005`` stays exact),
  * duplicate keys are errors, not silent overwrites,
  * every value and key has a (line, col), so schema and semantic errors print
    ``FILE:LINE:COL: error: message``,
  * hostile files end in such an error quickly and in little memory: only regular files of
    bounded size are read, nesting depth, alias expansion ("billion laughs"), entries per
    mapping and number length are bounded, and values echoed in messages are cut.

The events come from libyaml (``CParser``, about 10x faster than PyYAML's pure-Python scanner;
it keeps line and column marks) when PyYAML was built with it, else from the pure-Python
parser: the same events, so the same values, positions and errors. Building from events
instead of composed nodes keeps every step iterative (no recursion at any depth) and lets
aliases be counted as they are expanded.
"""

from __future__ import annotations

import os
import re
import stat
import time
from dataclasses import dataclass, field
from decimal import Decimal, InvalidOperation
from typing import TYPE_CHECKING, Any

import yaml

from ..errors import Diagnostic, InputError
from ..portable import O_BINARY, O_CLOEXEC, O_NONBLOCK
from .messages import clip, clip_message, clipped_repr

if TYPE_CHECKING:
    pass

# libyaml's parser when PyYAML has it; the pure-Python one gives the same events
FastLoader: type[yaml.SafeLoader] | type[yaml.CSafeLoader] = getattr(yaml, "CSafeLoader", yaml.SafeLoader)

# Limits on input (issue #11, hostile files). A real recipe or profile is far inside each one.
MAX_FILE_BYTES = 32 * 1024 * 1024  # a saved plan of 50,000 parameters is 13 MB; values are bounded below
MAX_DEPTH = 64  # nesting of mappings and lists; recipes need 5
MAX_ALIAS_NODES = 100_000  # values that aliases may add in total ("billion laughs" stops here)
MAX_ENTRIES = 65_536  # entries in one mapping or list: a device has 65,536 holding registers
MAX_NODES = 1_000_000  # values in one file (keys not counted): 15 per parameter of the largest profile
MAX_NUMBER_CHARS = 100  # a number written with more characters is refused (no 100,000-digit numbers)

Path_ = tuple[str | int, ...]

_STD = "tag:yaml.org,2002:"
_STR, _INT, _FLOAT, _BOOL, _NULL, _TIMESTAMP = (
    f"{_STD}{t}" for t in ("str", "int", "float", "bool", "null", "timestamp")
)
_MAP, _SEQ, _MERGE = f"{_STD}map", f"{_STD}seq", f"{_STD}merge"
_SCALAR_TAGS = {_STR, _INT, _FLOAT, _BOOL, _NULL, _TIMESTAMP}
MAX_EXPONENT = 400  # decimal exponents beyond any register value (a float64 ends near 1e308)
_NUMBER_START = frozenset("0123456789+-.")
_EXPONENT = re.compile(r"[-+]?(?:[0-9][0-9_]*(?:\.[0-9_]*)?|\.[0-9_]+)[eE][-+]?[0-9]+")  # YAML 1.2 floats 1.1 misses


Pos = int  # a position packed in one int: line << 24 | col (a tuple of two ints takes 3x the memory)


def pack(line: int, col: int) -> Pos:
    return line << 24 | col


def unpack(pos: Pos) -> tuple[int, int]:
    return pos >> 24, pos & 0xFFFFFF


@dataclass
class Source:
    """Positions of one loaded document: path tuple -> packed (line, col), 1-based; ``pos`` unpacks."""

    path: str
    values: dict[Path_, Pos] = field(default_factory=dict)
    keys: dict[Path_, Pos] = field(default_factory=dict)
    # YAML 1.1 booleans written as words (yes, no, on, off ...) by position: the text as written, so a
    # recipe can take 'yes' as the label it meant
    words: dict[Pos, str] = field(default_factory=dict)

    def word(self, at: Path_) -> str | None:
        """The text of a boolean at ``at`` when it was written as a word other than true/false."""
        return self.words.get(pack(*self.pos(at)))

    def pos(self, at: Path_, *, key: bool = False) -> tuple[int, int]:
        """(line, col) of the value (or key) at ``at``; falls back to the nearest parent."""
        table = self.keys if key else self.values
        p = tuple(at)
        while p:
            if p in table:
                return unpack(table[p])
            if p in self.values:
                return unpack(self.values[p])
            p = p[:-1]
        return unpack(self.values.get((), pack(1, 1)))

    def error(self, at: Path_, message: str, *, key: bool = False) -> Diagnostic:
        line, col = self.pos(at, key=key)
        return Diagnostic(self.path, line, col, clip_message(message))


class _Stop(Exception):
    """A limit was hit: stop building, report what was found so far."""


class _Frame:
    """One open mapping or list while building."""

    __slots__ = ("anchored", "at", "is_map", "key", "key_at", "skip_value", "value")

    def __init__(self, value: dict[str, Any] | list[Any], at: Path_, anchored: bool) -> None:
        self.value = value
        self.at = at
        self.is_map = isinstance(value, dict)
        self.anchored = anchored  # an anchor is open for this collection
        self.key: str | None = None  # a mapping's key waiting for its value
        self.key_at: Path_ = at  # its path: one tuple for the key's and the value's position
        self.skip_value = False  # the key was refused: drop its value


class _Anchor:
    __slots__ = ("at", "log", "nodes", "value")

    def __init__(self, value: Any, at: Path_, log: list[tuple[bool, Path_, Pos]], nodes: int) -> None:
        self.value, self.at, self.log, self.nodes = value, at, log, nodes


def _copy(value: Any) -> Any:
    if isinstance(value, dict):
        return {k: _copy(v) for k, v in value.items()}
    if isinstance(value, list):
        return [_copy(v) for v in value]
    return value


_MORE = object()  # _Builder._event: the document goes on


class _Builder:
    """Plain values with positions from a stream of YAML events; iterative, with limits."""

    def __init__(self, src: Source, loader: Any) -> None:
        self.src = src
        self.loader = loader
        self.errors: list[Diagnostic] = []
        self.nodes = 0  # values built, aliases included
        self.alias_nodes = 0
        self.anchors: dict[str, _Anchor] = {}
        self.open_anchors: list[tuple[str, int, int]] = []  # (name, log start, nodes at start)
        self.log: list[tuple[bool, Path_, Pos]] = []  # positions seen while an anchor is open
        self.tags: dict[tuple[str, tuple[bool, bool]], str] = {}

    def err(self, pos: Pos, message: str) -> None:
        line, col = unpack(pos)
        self.errors.append(Diagnostic(self.src.path, line, col, clip_message(message)))

    def put(self, is_key: bool, at: Path_, pos: Pos) -> None:
        (self.src.keys if is_key else self.src.values)[at] = pos
        if self.open_anchors:
            self.log.append((is_key, at, pos))

    def build(self) -> Any:
        """The document's value; the loader must stand before the document's root node."""
        get = self.loader.get_event
        stack: list[_Frame] = []
        scalar_event, tags, keys, values = yaml.ScalarEvent, self.tags, self.src.keys, self.src.values
        while True:
            ev: Any = get()
            # fast path, most events of a file: an unanchored plain scalar key or value in a mapping
            if ev.__class__ is scalar_event and ev.anchor is None and stack and not self.open_anchors:
                top = stack[-1]
                if top.is_map and not top.skip_value:
                    mark: Any = ev.start_mark
                    pos = (mark.line + 1) << 24 | (mark.column + 1)
                    out: dict[str, Any] = top.value  # type: ignore[assignment]
                    key = top.key
                    if key is not None:  # the value of that key
                        values[top.key_at] = pos
                        self.nodes += 1
                        if self.nodes > MAX_NODES:
                            self._too_many(pos)
                        out[key] = self._scalar(ev, pos)
                        top.key = None
                        continue
                    text = ev.value
                    tag = ev.tag
                    if tag is None or tag == "!":
                        tag = tags.get((text, ev.implicit)) or self._tag(ev)
                    if (
                        tag != _MERGE
                        and text not in out
                        and len(out) < MAX_ENTRIES
                        and (text[:1] != "0" or _leading_zero(text, tag, ev) is None)
                    ):
                        top.key_at = kat = (*top.at, text)
                        keys[kat] = pos
                        top.key = text
                        out[text] = None  # keeps the key's place (and finds duplicates) until its value
                        continue
                    # a refused key: the general path below says why
                elif not top.is_map and len(top.value) < MAX_ENTRIES:  # an item of a list
                    mark = ev.start_mark
                    pos = (mark.line + 1) << 24 | (mark.column + 1)
                    items: list[Any] = top.value  # type: ignore[assignment]
                    values[(*top.at, len(items))] = pos
                    self.nodes += 1
                    if self.nodes > MAX_NODES:
                        self._too_many(pos)
                    items.append(self._scalar(ev, pos))
                    continue
            if isinstance(ev, (yaml.MappingEndEvent, yaml.SequenceEndEvent)):
                frame = stack.pop()
                if frame.anchored:
                    self._end_anchor(frame.value, frame.at)
                if not stack:
                    return frame.value
                continue
            done = self._event(ev, stack)
            if done is not _MORE:
                return done

    def _event(self, ev: Any, stack: list[_Frame]) -> Any:
        """A key, value or item off the fast path: the document's value when it is complete, else ``_MORE``."""
        mark = ev.start_mark
        pos = (mark.line + 1) << 24 | (mark.column + 1)
        # where this event's value goes
        parent = stack[-1] if stack else None
        at: Path_ = ()
        if parent is not None:
            if parent.is_map and parent.key is None and not parent.skip_value:
                # this event is a key
                if not self._key(parent, ev, pos) and not isinstance(ev, yaml.ScalarEvent | yaml.AliasEvent):
                    self._skip()
                return _MORE
            if parent.is_map and parent.skip_value:
                if not isinstance(ev, yaml.ScalarEvent | yaml.AliasEvent):
                    self._skip()
                parent.skip_value = False
                return _MORE
            at = self._place(parent, pos)
        self.nodes += 1
        if self.nodes > MAX_NODES:
            self._too_many(pos)
        if isinstance(ev, yaml.AliasEvent):
            value = self._alias(ev, at, pos)
        elif isinstance(ev, yaml.ScalarEvent):
            self.put(False, at, pos)
            if ev.anchor is not None:
                self.open_anchors.append((ev.anchor, len(self.log), self.nodes - 1))
                self.log.append((False, at, pos))
            value = self._scalar(ev, pos)
            if ev.anchor is not None:
                self._end_anchor(value, at)
        elif isinstance(ev, (yaml.MappingStartEvent, yaml.SequenceStartEvent)):
            value = self._start(ev, at, pos, parent, stack)
            if value is _MORE:
                return _MORE
        else:  # pragma: no cover - the parser yields nothing else inside a document
            raise _Stop
        if parent is None:
            return value
        self._attach(parent, value)
        return _MORE

    def _place(self, parent: _Frame, pos: Pos) -> Path_:
        """Where a value inside ``parent`` goes: its key's path, or the next item of a list."""
        if parent.is_map:
            return parent.key_at if parent.key is not None else parent.at
        lst: list[Any] = parent.value  # type: ignore[assignment]
        if len(lst) >= MAX_ENTRIES:
            self.err(pos, f"more than {MAX_ENTRIES} entries in one list")
            raise _Stop
        return (*parent.at, len(lst))

    def _start(self, ev: Any, at: Path_, pos: Pos, parent: _Frame | None, stack: list[_Frame]) -> Any:
        """A mapping or list begins: a frame filled in place as its events arrive (``_MORE``), or None
        after a refused tag (its events skipped)."""
        if len(stack) >= MAX_DEPTH:
            self.err(pos, f"nested deeper than {MAX_DEPTH} levels")
            raise _Stop
        self.put(False, at, pos)
        if ev.anchor is not None:
            self.open_anchors.append((ev.anchor, len(self.log), self.nodes - 1))
            self.log.append((False, at, pos))
        is_map = isinstance(ev, yaml.MappingStartEvent)
        tag = ev.tag
        if tag is not None and tag != "!" and tag != (_MAP if is_map else _SEQ):
            self.err(pos, f"tag {clipped_repr(tag)} is not allowed")
            self._skip()
            if ev.anchor is not None:
                self._end_anchor(None, at)
            return None
        frame = _Frame({} if is_map else [], at, ev.anchor is not None)
        self._attach(parent, frame.value)
        stack.append(frame)
        return _MORE

    def _too_many(self, pos: Pos) -> None:
        self.err(pos, f"more than {MAX_NODES} values in one file")
        raise _Stop

    def _attach(self, parent: _Frame | None, value: Any) -> None:
        if parent is None:
            return
        if parent.is_map:
            key = parent.key
            assert key is not None
            parent.value[key] = value  # type: ignore[call-overload]
            parent.key = None
        else:
            parent.value.append(value)  # type: ignore[union-attr]

    def _key(self, parent: _Frame, ev: Any, pos: Pos) -> bool:
        """Take a mapping key; False (and the value is dropped) when it is refused."""
        parent.skip_value = True
        if not isinstance(ev, yaml.ScalarEvent):
            self.err(pos, "a mapping key must be a plain scalar")
            return False
        tag = self._tag(ev)
        if tag == _MERGE:
            self.err(pos, "YAML merge keys ('<<') are not supported; use 'extends'")
            return False
        why = _leading_zero(str(ev.value), tag, ev)
        if why is not None:
            self.err(pos, why)
            return False
        key = str(ev.value)
        if ev.anchor is not None:
            self.anchors[ev.anchor] = _Anchor(key, (), [], 1)
        out: dict[str, Any] = parent.value  # type: ignore[assignment]
        if key in out:
            line, _ = unpack(self.src.keys[(*parent.at, key)])
            self.err(pos, f"duplicate key '{clip(key)}' (first at line {line})")
            return False
        if len(out) >= MAX_ENTRIES:
            self.err(pos, f"more than {MAX_ENTRIES} entries in one mapping (a device has {MAX_ENTRIES} registers)")
            raise _Stop
        parent.key_at = kat = (*parent.at, key)
        self.put(True, kat, pos)
        parent.key = key
        parent.skip_value = False
        out[key] = None  # keeps the key's place (and finds duplicates) until its value is built
        return True

    def _skip(self) -> None:
        """Drop the rest of a collection whose start event was just read (within the depth limit)."""
        depth = 1
        get = self.loader.get_event
        while depth:
            ev = get()
            if isinstance(ev, (yaml.MappingStartEvent, yaml.SequenceStartEvent)):
                depth += 1
                if depth > MAX_DEPTH:
                    mark: Any = ev.start_mark
                    self.err(pack(mark.line + 1, mark.column + 1), f"nested deeper than {MAX_DEPTH} levels")
                    raise _Stop
            elif isinstance(ev, (yaml.MappingEndEvent, yaml.SequenceEndEvent)):
                depth -= 1

    def _end_anchor(self, value: Any, at: Path_) -> None:
        name, start, nodes_before = self.open_anchors.pop()
        self.anchors[name] = _Anchor(value, at, self.log[start:], self.nodes - nodes_before)
        if not self.open_anchors:
            self.log.clear()

    def _alias(self, ev: Any, at: Path_, pos: Pos) -> Any:
        anchor = self.anchors.get(ev.anchor)
        if anchor is None:
            open_names = {name for name, _, _ in self.open_anchors}
            why = "refers to itself" if ev.anchor in open_names else "is not defined before this point"
            self.err(pos, f"alias '*{clip(ev.anchor)}' {why}")
            return None
        self.alias_nodes += anchor.nodes
        if self.alias_nodes > MAX_ALIAS_NODES:
            self.err(pos, f"aliases expand to more than {MAX_ALIAS_NODES} values (an alias bomb?)")
            raise _Stop
        self.nodes += anchor.nodes - 1
        cut = len(anchor.at)
        for is_key, p, ppos in anchor.log:
            self.put(is_key, at + p[cut:], ppos)
        return _copy(anchor.value)

    def _tag(self, ev: Any) -> str:
        tag: str | None = ev.tag
        if tag is None or tag == "!":
            text: str = ev.value
            if ev.implicit[0] and text.isdigit() and text.isascii() and (text[0] != "0" or len(text) == 1):
                return _INT  # a plain decimal integer (registers, counts): what YAML 1.1's int pattern says
            k = (text, ev.implicit)
            tag = self.tags.get(k)
            if tag is None:
                tag = self.tags[k] = self.loader.resolve(yaml.ScalarNode, text, ev.implicit)
        return tag

    def _scalar(self, ev: Any, pos: Pos) -> Any:
        tag = ev.tag
        if tag is None or tag == "!":
            tag = self.tags.get((ev.value, ev.implicit)) or self._tag(ev)
        if tag not in _SCALAR_TAGS:
            self.err(pos, f"tag {clipped_repr(tag)} is not allowed")
            return None
        text: str = ev.value
        if text[:1] in ("0", "+", "-") and tag in (_INT, _STR):
            why = _leading_zero(text, tag, ev)
            if why is not None:
                self.err(pos, why)
                return None
        if tag == _STR and text[:1] in _NUMBER_START and not ev.style and _EXPONENT.fullmatch(text):
            tag = _FLOAT  # 1e-30: text to YAML 1.1 (it wants 1.0e-30), a number to YAML 1.2 and to people
        if tag in (_STR, _TIMESTAMP):
            return text
        if tag == _NULL:
            return None
        if tag == _BOOL:
            if text.lower() not in ("true", "false"):
                self.src.words[pos] = text
            return text.lower() in ("true", "yes", "on", "y")
        if len(text) > MAX_NUMBER_CHARS:
            self.err(pos, f"number too long ({len(text)} characters; at most {MAX_NUMBER_CHARS}): {clip(text)}")
            return None
        if tag == _INT:
            try:
                return _int(text)
            except (ValueError, TypeError):
                self.err(pos, f"not an integer: {clipped_repr(text)}")
                return None
        # float: keep the exact decimal text
        t = text.replace("_", "")
        if t.lower() in (".inf", "+.inf", "-.inf", ".nan"):
            self.err(pos, f"{text} is not a finite number")
            return None
        try:
            d = Decimal(t)
        except InvalidOperation:
            self.err(pos, f"not a number: {clipped_repr(text)}")
            return None
        if d and not -MAX_EXPONENT <= d.adjusted() <= MAX_EXPONENT:  # 1e999999999: no register holds it, and
            # decimal arithmetic on it overflows
            self.err(
                pos,
                f"{clip(text)} is too {'large' if d.adjusted() > 0 else 'close to 0'} "
                f"(exponents -{MAX_EXPONENT}..{MAX_EXPONENT})",
            )
            return None
        return d


def _leading_zero(text: str, tag: str, ev: Any) -> str | None:
    """Why a plain integer with a leading zero is refused: YAML 1.1 (PyYAML, so us) reads 010 as octal 8,
    YAML 1.2 and most other tools as 10, and 0o17 as text; nobody should have to know which."""
    if ev.style:  # quoted or a block scalar: text, as written (plain is None, or "" from libyaml)
        return None
    t = text.replace("_", "").lstrip("+-")
    if len(t) < 2 or t[0] != "0":
        return None
    sign = "-" if text.startswith("-") else ""
    if tag == _INT and t[1].isdigit():  # YAML 1.1 octal
        d, o = int(sign + t, 10), _int(text)
        if d == o:  # 00, 07: the same either way, but say it plainly
            return f"'{text}' has a leading zero; write {d}, or quote it if it is text"
        return (
            f"'{text}' has a leading zero: YAML 1.1 reads it as octal ({o}), other tools as {d}; write {d} "
            f"(or {sign}0x{abs(o):X} for {o}), or quote it if it is text"
        )
    if tag == _STR and t.isdigit():  # 08, 09: not octal, text in YAML 1.1, a number to a reader
        return f"'{text}' has a leading zero; write {int(sign + t)}, or quote it if it is text"
    if tag == _STR and t[1] in "oO" and len(t) > 2 and all(c in "01234567" for c in t[2:]):
        o = int(sign + t[2:], 8)
        return (
            f"'{text}' is octal {o} in YAML 1.2 but text in YAML 1.1; write {o} (or {sign}0x{abs(o):X}), "
            "or quote it if it is text"
        )
    return None


def _int(text: str) -> int:
    """YAML 1.1 integers as PyYAML resolves them: 0x1F, 0o17 / 017, 0b101, 1_000, +5."""
    t = text.replace("_", "")
    sign = -1 if t.startswith("-") else 1
    t = t.lstrip("+-")
    if t.startswith(("0x", "0X")):
        return sign * int(t[2:], 16)
    if t.startswith(("0b", "0B")):
        return sign * int(t[2:], 2)
    if t.startswith(("0o", "0O")):
        return sign * int(t[2:], 8)
    if ":" in t:  # sexagesimal 1:30 -> 90
        total = 0
        for part in t.split(":"):
            total = total * 60 + int(part)
        return sign * total
    if len(t) > 1 and t.startswith("0"):
        return sign * int(t, 8)
    return sign * int(t)


def read_text(path: str) -> str:
    """Read a UTF-8 file; problems become diagnostics.

    Only regular files are read, and only after their size is known to be within the limit:
    ``/dev/zero``, FIFOs and devices never block or fill memory.
    """
    try:
        # O_NONBLOCK: opening a FIFO must not wait for a writer; O_BINARY: Windows reads the bytes as they are
        fd = os.open(path, os.O_RDONLY | O_NONBLOCK | O_CLOEXEC | O_BINARY)
    except FileNotFoundError:
        raise InputError([Diagnostic(path, 0, 0, "no such file")]) from None
    except IsADirectoryError:
        raise InputError([Diagnostic(path, 0, 0, "is a directory, not a file")]) from None
    except PermissionError as e:  # Windows opens no folder as a file: "Permission denied"
        why = "is a directory, not a file" if os.path.isdir(path) else f"cannot read: {e.strerror}"
        raise InputError([Diagnostic(path, 0, 0, why)]) from None
    except OSError as e:
        raise InputError([Diagnostic(path, 0, 0, f"cannot read: {e.strerror}")]) from None
    try:
        st = os.fstat(fd)
        if stat.S_ISDIR(st.st_mode):
            raise InputError([Diagnostic(path, 0, 0, "is a directory, not a file")])
        if not stat.S_ISREG(st.st_mode):
            raise InputError([Diagnostic(path, 0, 0, "not a regular file (a device, FIFO or socket)")])
        if st.st_size > MAX_FILE_BYTES:
            raise InputError(
                [
                    Diagnostic(
                        path,
                        1,
                        1,
                        f"file too large ({st.st_size / 1e6:.1f} MB; limit {MAX_FILE_BYTES // (1024 * 1024)} MiB)",
                    )
                ]
            )
        chunks = []
        left = MAX_FILE_BYTES + 1  # the file may grow while we read
        while left > 0:
            chunk = os.read(fd, min(left, 1 << 20))
            if not chunk:
                break
            chunks.append(chunk)
            left -= len(chunk)
        data = b"".join(chunks)
        if len(data) > MAX_FILE_BYTES:
            raise InputError(
                [Diagnostic(path, 1, 1, f"file too large (more than {MAX_FILE_BYTES // (1024 * 1024)} MiB)")]
            )
    except OSError as e:
        raise InputError([Diagnostic(path, 0, 0, f"cannot read: {e.strerror}")]) from None
    finally:
        os.close(fd)
    try:
        return data.decode("utf-8-sig")
    except UnicodeDecodeError as e:
        before = data[: e.start]
        line = before.count(b"\n") + 1
        col = e.start - (before.rfind(b"\n") + 1) + 1
        raise InputError([Diagnostic(path, line, col, f"not UTF-8 text (byte 0x{data[e.start]:02x})")]) from None


# A libyaml error within this many bytes of the start is found again by the pure-Python parser (about
# 1 MB/s: a second at most, on an error), whose diagnostics are then the answer: both parsers give one,
# whatever libyaml's version. Recipes and profiles are far smaller; past it libyaml's position stands.
_REPARSE_BYTES = 1024 * 1024


def _python_error(text: str, err: yaml.MarkedYAMLError) -> yaml.MarkedYAMLError:
    """The pure-Python parser's wording of a syntax error libyaml found where the whole file is not parsed
    again (past ``_REPARSE_BYTES``, or before a character the pure-Python reader refuses up front).

    Only the message is taken, and only when both stop at the same place; else libyaml's stands.
    """
    mark = err.problem_mark or err.context_mark
    if mark is None:
        return err
    depth = 0
    deadline = time.monotonic() + 0.25
    try:  # the pure-Python scanner is quadratic in nesting depth: stop where the builder would
        for i, ev in enumerate(yaml.parse(text, Loader=yaml.SafeLoader)):
            if isinstance(ev, yaml.CollectionStartEvent):
                depth += 1
                if depth > MAX_DEPTH:
                    return err
            elif isinstance(ev, yaml.CollectionEndEvent):
                depth -= 1
            if i % 256 == 0 and time.monotonic() > deadline:
                return err
    except yaml.MarkedYAMLError as e:
        mine = e.problem_mark or e.context_mark
        if mine is not None and (mine.line, mine.column) == (mark.line, mark.column):
            return e
    except yaml.YAMLError:  # the pure-Python reader refuses the whole text at once (a NUL after the error)
        return err
    return err


def _reader_error(path: str, text: str, e: yaml.reader.ReaderError) -> Diagnostic:
    """A character YAML does not allow (a NUL, a control character), at its line and column, worded alike
    whichever parser PyYAML has (libyaml finds it while parsing, the pure-Python reader before)."""
    pos = max(0, min(int(e.position), len(text)))
    line = text.count("\n", 0, pos) + 1
    col = pos - (text.rfind("\n", 0, pos) + 1) + 1
    char = e.character if isinstance(e.character, int) else ord(str(e.character)[:1] or "\0")
    return Diagnostic(path, line, col, f"invalid YAML: character #x{char:04X} is not allowed in a YAML file")


# documents loaded with hand_over=True, for the next load of the same unchanged file (once)
_handed_over: dict[str, tuple[tuple[int, int, int], Any, Source]] = {}


def file_stamp(path: str) -> tuple[int, int, int] | None:
    """What changes when a file does (its inode, size and modification time); None when it is not there."""
    try:
        st = os.stat(path)
    except OSError:
        return None
    return st.st_ino, st.st_size, st.st_mtime_ns


def forget(path: str | os.PathLike[str]) -> None:
    """Drop a document kept by ``load(..., hand_over=True)`` that nobody loaded again."""
    _handed_over.pop(os.fspath(path), None)


def load(
    path: str | os.PathLike[str], text: str | None = None, *, loader: type[Any] = FastLoader, hand_over: bool = False
) -> tuple[Any, Source]:
    """Load one YAML (or JSON, a subset) document. Raises InputError.

    ``loader``: a PyYAML loader class (``yaml.SafeLoader`` forces the pure-Python parser).
    ``hand_over``: keep the result for the next ``load`` of this file, if it is unchanged by then
    (``validate`` looks at a file to tell its kind, then the right loader loads it: parsed once).
    The caller must then only read the value: the next loader gets the same objects.
    """
    p = os.fspath(path)
    if text is None and p in _handed_over:
        stamp, kept, kept_src = _handed_over.pop(p)
        if stamp == file_stamp(p):
            return kept, kept_src
    stamp_before = file_stamp(p) if hand_over else None
    if text is None:
        text = read_text(p)
    src = Source(p)
    try:
        ldr = loader(text)  # the pure-Python reader checks every character of the text here
    except yaml.reader.ReaderError as e:
        raise InputError([_reader_error(p, text, e)]) from None
    b = _Builder(src, ldr)
    value: Any = None
    try:
        ldr.get_event()  # StreamStart
        if ldr.check_event(yaml.StreamEndEvent):
            raise InputError([Diagnostic(p, 1, 1, "the file is empty")])
        ldr.get_event()  # DocumentStart
        value = b.build()
        ldr.get_event()  # DocumentEnd
        if not ldr.check_event(yaml.StreamEndEvent):
            ev = ldr.get_event()
            raise InputError(
                [
                    Diagnostic(
                        p,
                        ev.start_mark.line + 1,
                        ev.start_mark.column + 1,
                        "expected a single document in the file, found another one",
                    )
                ]
            )
    except yaml.MarkedYAMLError as e:
        if loader is not yaml.SafeLoader:
            # libyaml reads ahead and has limits of its own that change between releases (the one in
            # PyYAML 6.0.4 stops at 1,000 nested levels before we see the 65th): ask the pure-Python parser, whose
            # events the builder checks one by one, so our limits and positions apply first
            mark = e.problem_mark or e.context_mark
            if mark is None or mark.index <= _REPARSE_BYTES:
                try:
                    return load(p, text, loader=yaml.SafeLoader, hand_over=hand_over)
                except InputError as again:
                    first = again.diagnostics[0]
                    # the pure-Python reader refuses a bad character anywhere before it parses: when
                    # that lies past libyaml's error, libyaml's came first in the file and stands
                    if mark is None or (first.line, first.col) <= (mark.line + 1, mark.column + 1):
                        raise
            e = _python_error(text, e)
        mark = e.problem_mark or e.context_mark
        line, col = (mark.line + 1, mark.column + 1) if mark else (1, 1)
        b.errors.append(Diagnostic(p, line, col, f"invalid YAML: {clip(str(e.problem or e.context), 200)}"))
    except yaml.reader.ReaderError as e:
        b.errors.append(_reader_error(p, text, e))
    except yaml.YAMLError as e:
        b.errors.append(Diagnostic(p, 1, 1, f"invalid YAML: {clip(str(e), 200)}"))
    except _Stop:
        pass
    finally:
        ldr.dispose()
    if b.errors:
        raise InputError(b.errors)
    if stamp_before is not None and stamp_before == file_stamp(p):
        _handed_over[p] = (stamp_before, value, src)
    return value, src
