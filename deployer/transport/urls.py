"""Device URLs (and the errors of transports, from deployer.errors), without pymodbus.

Parsing a URL (plan, validate, inventories) must not cost importing pymodbus; transport.py
re-exports everything here.
"""

from __future__ import annotations

import difflib
import functools
import ipaddress
import os
import re
import socket
import urllib.parse
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from typing import Any

from ..errors import BadURL
from ..limits import LIMITS
from ..load.durations import parse_duration


@dataclass(frozen=True)
class LineSettings:
    """A serial line's settings, the URL's options over SERIAL_DEFAULTS."""

    baudrate: int
    bytesize: int
    parity: str
    stopbits: int

    def __str__(self) -> str:
        return (
            f"{self.baudrate} baud, {self.bytesize} data bits, parity {self.parity}, "
            f"{self.stopbits} stop bit{'s' if self.stopbits != 1 else ''}"
        )


SERIAL_DEFAULTS = LineSettings(19200, 8, "N", 1)  # rtu:// and ascii:// alike
DEFAULT_TIMEOUT = 1.0  # seconds per attempt
DEFAULT_RETRIES = 2


@dataclass(frozen=True)
class DeviceURL:
    scheme: str  # tcp | tls | rtu | ascii | rtu+tcp
    host: str | None = None
    port: int | None = None
    path: str | None = None  # serial device
    options: dict[str, str] = field(default_factory=dict)
    timeout: float = DEFAULT_TIMEOUT
    retries: int = DEFAULT_RETRIES

    @property
    def bus(self) -> str:
        """Key of the half-duplex bus this device sits on; devices on one bus never talk at once."""
        if self.scheme in ("rtu", "ascii"):
            # a symlink (/dev/serial/by-id/..., a socat link) is the same wire as its target; a Windows
            # port is its name (COM3, com3 and \\.\COM3 are one port), never a file in the working folder
            path = self.path or ""
            if windows_port(path):
                return f"serial:{windows_port(path)}"
            return f"serial:{path if '://' in path else os.path.realpath(path)}"
        if self.scheme == "rtu+tcp":
            return f"gateway:{self.host}:{self.port}"
        return f"{self.scheme}:{self.host}:{self.port}"

    @property
    def serial_device(self) -> str:
        r"""What to open for rtu/ascii: the path, or a Windows port in the device namespace (\\.\COM10:
        COM10 and above cannot be opened by their bare name, and \\.\COM3 works as well as COM3)."""
        port = windows_port(self.path or "")
        return f"\\\\.\\{port}" if port else self.path or ""

    @property
    def lock_keys(self) -> tuple[str, ...]:
        """What this URL reaches, however it is spelled: the bus keys with host names resolved.

        tcp://localhost:P, tcp://127.0.0.1:P, tcp://127.1:P and tcp://2130706433:P are one device;
        a name with several addresses (localhost: 127.0.0.1 and ::1) gives one key for each, so a run
        by any of them excludes the others. Serial paths are already real paths (``bus``).
        """
        if self.scheme in ("rtu", "ascii") or self.host is None:
            return (self.bus,)
        kind = "gateway" if self.scheme == "rtu+tcp" else self.scheme
        return tuple(f"{kind}:{a}:{self.port}" for a in _addresses(self.host))

    @property
    def shared_bus(self) -> bool:
        return self.scheme in ("rtu", "ascii", "rtu+tcp")

    @property
    def line(self) -> LineSettings:
        """Serial line settings (rtu, ascii; for other schemes only the defaults, used for timing)."""
        o = self.options
        d = SERIAL_DEFAULTS
        return LineSettings(
            int(o.get("baudrate", d.baudrate)),
            int(o.get("bytesize", d.bytesize)),
            o.get("parity", d.parity),
            int(o.get("stopbits", d.stopbits)),
        )


# COM1..COM256 as Windows names them, bare or in the device namespace (\\.\COM10); any other
# \\.\NAME is a Windows device too (com0com's CNCA0)
_COM = re.compile(r"(?:\\\\\.\\)?(COM[1-9][0-9]{0,2})", re.IGNORECASE)
_DEVICE_NAMESPACE = re.compile(r"\\\\\.\\([A-Za-z0-9_]+)")


def windows_port(path: str) -> str | None:
    """The Windows port name a serial URL's path names (COM3, COM10, CNCA0), or None for a file path."""
    m = _COM.fullmatch(path)
    if m:
        return m.group(1).upper()
    m = _DEVICE_NAMESPACE.fullmatch(path)
    return m.group(1).upper() if m else None


@functools.lru_cache(maxsize=512)
def _addresses(host: str) -> tuple[str, ...]:
    """The host's addresses, canonical (IPv6 in brackets), sorted; the name itself when it does not resolve."""
    try:
        infos = socket.getaddrinfo(host, None, type=socket.SOCK_STREAM)
    except (OSError, UnicodeError):
        return (host.lower(),)  # the connection will fail and say so; the spelling is the best key left
    out = set()
    for info in infos:
        ip = ipaddress.ip_address(str(info[4][0]).split("%")[0])
        if isinstance(ip, ipaddress.IPv6Address) and ip.ipv4_mapped is not None:
            ip = ip.ipv4_mapped
        out.add(f"[{ip.compressed}]" if ip.version == 6 else ip.compressed)
    return tuple(sorted(out)) or (host.lower(),)


def no_answer_hint(url: DeviceURL, unit: int) -> str:
    """What to check when a device does not answer: on serial lines, mostly the line settings and unit id."""
    if url.scheme in ("rtu", "ascii"):
        return (
            f" at {url.line}, unit {unit}: check that the device uses the same baud rate, parity, data bits "
            f"and stop bits and answers to unit {unit} (URL options baudrate, parity, bytesize, stopbits; "
            f"--unit)"
        )
    if url.scheme == "rtu+tcp":
        return (
            f" through the gateway, unit {unit}: check the unit id and that the gateway's serial line "
            f"settings (baud rate, parity, data bits, stop bits) match the device's"
        )
    return ""


# ---- URLs ----------------------------------------------------------------------------------

DEFAULT_PORTS = {"tcp": 502, "tls": 802}
_COMMON = {"timeout", "retries", "pause_after_connect", "pause_between_requests", "device_identification"}
_OPTIONS: dict[str, set[str]] = {
    "tcp": _COMMON,
    "tls": _COMMON | {"cert", "key", "ca", "verify", "server_hostname"},  # server_hostname: name to verify
    "rtu": _COMMON | {"baudrate", "parity", "bytesize", "stopbits"},
    "ascii": _COMMON | {"baudrate", "parity", "bytesize", "stopbits"},
    "rtu+tcp": _COMMON,
}
# numeric options: (type, lowest, highest); docs/urls.md shows the same ranges (a test compares them)
NUMERIC_OPTIONS: dict[str, tuple[type[int] | type[float], float, float]] = {
    # a URL's timeout and retries within the bounds every caller has (deployer.LIMITS)
    "timeout": (float, 0.001, LIMITS.timeout.high),
    "retries": (int, int(LIMITS.retries.low), int(LIMITS.retries.high)),
    "baudrate": (int, 50, 4_000_000),
    "bytesize": (int, 5, 8),
    "stopbits": (int, 1, 2),
}


def option_facts(option: str) -> tuple[list[str], str | None, str | None]:
    """(schemes that take it, its default, what it allows) for a URL option: what `explain` shows."""
    schemes = [s for s, opts in _OPTIONS.items() if option in opts]
    line = SERIAL_DEFAULTS
    defaults = {
        "timeout": DEFAULT_TIMEOUT,
        "retries": DEFAULT_RETRIES,
        "baudrate": line.baudrate,
        "pause_after_connect": "the profile's limits.pause_after_connect (0)",
        "pause_between_requests": "the profile's limits.pause_between_requests (0)",
        "bytesize": line.bytesize,
        "parity": line.parity,
        "stopbits": line.stopbits,
        "verify": "true",
        "server_hostname": "the URL's host",
        "device_identification": "the profile's limits.device_identification (true)",
    }
    allowed = {
        "parity": "N, E, O",
        "pause_after_connect": "a duration: 250ms, 1s (a bare number is seconds)",
        "pause_between_requests": "a duration: 250ms, 1s (a bare number is seconds)",
        "verify": "true, false (also 1, 0, yes, no)",
        "device_identification": "true, false (also 1, 0, yes, no)",
        "cert": "a PEM file",
        "key": "a PEM file",
        "ca": "a PEM file",
    }
    default = defaults.get(option)
    return (
        schemes,
        None if default is None else str(default),
        (range_text(option) if option in NUMERIC_OPTIONS else allowed.get(option)),
    )


def range_text(option: str) -> str:
    """'50..4000000', '0.001..600': a numeric option's allowed range as users write numbers."""
    _, lo, hi = NUMERIC_OPTIONS[option]
    return "..".join(str(int(x)) if float(x).is_integer() else f"{x:g}" for x in (lo, hi))


def parse_url(text: str, *, timeout: float | None = None, retries: int | None = None) -> DeviceURL:
    """Parse a device URL (docs/urls.md). Raises BadURL with a precise message.

    ``timeout`` / ``retries`` apply where the URL itself does not set them.
    """
    u, scheme = _split(text)
    options = _options(text, u.query, scheme)
    for key in ("pause_after_connect", "pause_between_requests"):
        if key in options:
            try:
                parse_duration(options[key])
            except ValueError as e:
                raise BadURL(f"option {key}: {e}") from None
    if "device_identification" in options and options["device_identification"].lower() not in _TRUTH:
        raise BadURL(
            f"option device_identification: {options['device_identification']!r} is none of true, false, 1, 0, yes, no"
        )
    to = _number(options, "timeout") if "timeout" in options else (timeout if timeout is not None else DEFAULT_TIMEOUT)
    rt = _number(options, "retries") if "retries" in options else (retries if retries is not None else DEFAULT_RETRIES)
    if scheme in ("rtu", "ascii"):
        return DeviceURL(scheme, path=_serial_path(u, scheme, options), options=options, timeout=to, retries=rt)
    host, port = _host_port(text, u, scheme)
    if scheme == "tls":
        _check_tls(options)
    return DeviceURL(scheme, host=host, port=port, options=options, timeout=to, retries=rt)


def _split(text: str) -> tuple[urllib.parse.SplitResult, str]:
    """The URL's parts and its (known) scheme; no fragment, no user name."""
    raw = text.strip()
    if "://" not in raw:
        raise BadURL(f"'{text}' is not a device URL (expected e.g. tcp://HOST:502 or rtu:///dev/ttyUSB0)")
    try:
        u = urllib.parse.urlsplit(raw)
    except ValueError as e:  # "Invalid IPv6 URL": an unclosed [
        raise BadURL(
            f"'{text}' is not a valid URL ({e}; an IPv6 host is written in brackets: tcp://[::1]:502)"
        ) from None
    scheme = u.scheme.lower()
    if scheme not in _OPTIONS:
        hint = difflib.get_close_matches(scheme, list(_OPTIONS), n=1)
        raise BadURL(
            f"unknown scheme '{scheme}' in '{text}'"
            + (f"; did you mean '{hint[0]}'?" if hint else f" (known: {', '.join(_OPTIONS)})")
        )
    if u.fragment or raw.endswith("#"):
        raise BadURL(f"unexpected '#{u.fragment}' in '{text}' (a device URL has no fragment; options go after ?)")
    if "@" in u.netloc:
        raise BadURL(f"unexpected user name or password in '{text}' (Modbus has no login; TLS uses cert= and key=)")
    return u, scheme


def _options(text: str, query: str, scheme: str) -> dict[str, str]:
    """The query's options: each known to the scheme, each given once."""
    options: dict[str, str] = {}
    for key, values in urllib.parse.parse_qs(query, keep_blank_values=True).items():
        if len(values) > 1:
            raise BadURL(f"option '{key}' given {len(values)} times in '{text}': give it once")
        if key not in _OPTIONS[scheme]:
            hint = difflib.get_close_matches(key, sorted(_OPTIONS[scheme]), n=1)
            raise BadURL(
                f"unknown option '{key}' in {scheme} URL"
                + (f"; did you mean '{hint[0]}'?" if hint else f" (known: {', '.join(sorted(_OPTIONS[scheme]))})")
            )
        options[key] = values[-1]
    return options


def _number(options: Mapping[str, str], key: str) -> Any:
    kind, lo, hi = NUMERIC_OPTIONS[key]
    try:
        v = kind(options[key])
    except ValueError:
        raise BadURL(f"option {key}={options[key]!r} is not a{'n integer' if kind is int else ' number'}") from None
    if not lo <= v <= hi:
        raise BadURL(f"option {key}={options[key]} is out of range ({range_text(key)})")
    return v


def _serial_path(u: urllib.parse.SplitResult, scheme: str, options: dict[str, str]) -> str:
    """rtu:// and ascii://: the serial device (Windows ports as Windows opens them), the line options checked."""
    path = urllib.parse.unquote(u.netloc + u.path)
    if not path:
        raise BadURL(f"{scheme} URL needs a serial device path: {scheme}:///dev/ttyUSB0 or {scheme}://COM3")
    win = windows_port(path)
    if win is not None:  # COMn is kept as its name (``serial_device`` opens \\.\COMn), others as \\.\NAME
        path = win if _COM.fullmatch(win) else "\\\\.\\" + win
    for key in ("baudrate", "bytesize", "stopbits"):
        if key in options:
            _number(options, key)
    if "parity" in options:
        options["parity"] = options["parity"].upper()
        if options["parity"] not in ("N", "E", "O"):
            raise BadURL(f"option parity={options['parity']} must be N, E or O")
    return path


def _host_port(text: str, u: urllib.parse.SplitResult, scheme: str) -> tuple[str, int]:
    try:
        host, port = u.hostname, u.port
    except ValueError:
        raise BadURL(f"bad port in '{text}'") from None
    if not host:
        raise BadURL(f"{scheme} URL needs a host: {scheme}://HOST:PORT")
    if u.path not in ("", "/"):
        raise BadURL(f"unexpected path '{u.path}' in {scheme} URL")
    if port == 0:
        raise BadURL(f"bad port in '{text}' (1..65535)")
    if port is None:
        if scheme == "rtu+tcp":
            raise BadURL("rtu+tcp URL needs a port: rtu+tcp://HOST:PORT (the gateway's TCP port)")
        port = DEFAULT_PORTS[scheme]
    return host, port


def _check_tls(options: Mapping[str, str]) -> None:
    if "verify" in options and options["verify"].lower() not in ("true", "false", "1", "0", "yes", "no"):
        raise BadURL(f"option verify={options['verify']} must be true or false")
    for key in ("cert", "key", "ca"):
        if key in options and not os.path.isfile(options[key]):
            if os.path.exists(options[key]):
                raise BadURL(f"tls option {key}: '{options[key]}' is not a regular file (expected a PEM file)")
            raise BadURL(f"tls option {key}: no such file '{options[key]}'")
    if ("cert" in options) != ("key" in options):
        raise BadURL("tls options cert and key go together (the client certificate and its key)")


def pacing(url: DeviceURL, after_connect_ms: float = 0, between_ms: float = 0) -> tuple[float, float]:
    """Seconds of (pause after connecting, least gap between requests): the URL's options, else the
    profile's ``limits`` given here."""
    o = url.options
    after = parse_duration(o["pause_after_connect"]) if "pause_after_connect" in o else after_connect_ms / 1000
    between = parse_duration(o["pause_between_requests"]) if "pause_between_requests" in o else between_ms / 1000
    return after, between


def describe(url: DeviceURL) -> str:
    """The URL as text without secrets: no key/cert/CA file paths; serial line settings are kept."""
    if url.scheme in ("rtu", "ascii"):
        opts = {k: v for k, v in url.options.items() if k not in _COMMON}
        q = ("?" + "&".join(f"{k}={v}" for k, v in sorted(opts.items()))) if opts else ""
        return f"{url.scheme}://{url.path}{q}"
    host = f"[{url.host}]" if url.host and ":" in url.host else url.host
    q = "?verify=false" if url.scheme == "tls" and not verify(url) else ""
    return f"{url.scheme}://{host}:{url.port}{q}"


def recorded(url: DeviceURL, described: str | None = None) -> str:
    """``describe(url)`` (``described``, when the caller has it) with what it takes to talk to the device again: its
    timeout and retries where they are not the defaults (from the URL or an inventory's defaults), its pauses and
    ``device_identification`` as the URL gave them. What a snapshot keeps: ``rollback SNAPSHOT`` of a slow gateway
    is paced as the apply was."""
    text = describe(url) if described is None else described
    extra = {k: v for k, v in url.options.items() if k in _COMMON and k not in ("timeout", "retries")}
    if url.timeout != DEFAULT_TIMEOUT:
        extra["timeout"] = f"{url.timeout:g}"
    if url.retries != DEFAULT_RETRIES:
        extra["retries"] = str(url.retries)
    if not extra:
        return text
    q = urllib.parse.urlencode(sorted(extra.items()), safe="")
    return f"{text}&{q}" if "?" in text else f"{text}?{q}"


def overridden(url: DeviceURL, timeout: float | None, retries: int | None) -> DeviceURL:
    """``url`` with the ``timeout``/``retries`` a person gave now over the ones the URL recorded (a snapshot's)."""
    options = dict(url.options)
    if timeout is not None:
        options.pop("timeout", None)
    if retries is not None:
        options.pop("retries", None)
    return replace(
        url,
        options=options,
        timeout=url.timeout if timeout is None else timeout,
        retries=url.retries if retries is None else retries,
    )


_TRUTH = {"true": True, "1": True, "yes": True, "false": False, "0": False, "no": False}


def identification(url: DeviceURL) -> bool | None:
    """The URL's ``device_identification`` option: whether the device is asked Function 43 (None: not said)."""
    text = url.options.get("device_identification")
    return None if text is None else _TRUTH[text.lower()]


def verify(url: DeviceURL) -> bool:
    """tls: whether the server certificate is checked (verify=false turns it off)."""
    return url.options.get("verify", "true").lower() in ("true", "1", "yes")
