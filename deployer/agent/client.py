"""The agent's HTTP API from the client side, on the standard library (``urllib``): the command line's
``--agent URL``, the Python API (``deployer.Agent``) and the Ansible modules share it.

Every refusal comes back as ``AgentError`` with the exit code the same command has without the agent.
"""

from __future__ import annotations

import json
import urllib.parse
from collections.abc import Callable, Iterator, Mapping
from typing import TYPE_CHECKING, Any, Literal

from ..calls import checked
from ..errors import EXIT_UNREACHABLE, AgentError

if TYPE_CHECKING:
    import ssl
    import urllib.error

# ssl and urllib.request (with http.client and email) are loaded by the first request: every command imports this
# module through deployer.api, and they were a fifth of an offline command's start-up (validate, plan)

ENV = "DEPLOYER_AGENT"


class Agent:
    """A client of one site agent: ``Agent("http://127.0.0.1:8470")``; ``token``: the agent's token (or a user's);
    without one, for a loopback URL, the token an agent of this user made itself (``local_token.find``);
    ``ca`` (a PEM file) for an ``https://`` agent whose certificate the system's CAs do not vouch for; ``cert`` and
    ``key`` (PEM files): a TLS client certificate, for an agent that maps certificates to users.

    Methods map the HTTP API one to one (docs/agent.md); ``apply`` starts a run and follows it to its end.
    """

    @checked("Agent")
    def __init__(
        self,
        url: str,
        *,
        token: str | None = None,
        ca: str | None = None,
        timeout: float = 30.0,
        cert: str | None = None,
        key: str | None = None,
    ) -> None:
        u = urllib.parse.urlsplit(url)
        if u.scheme not in ("http", "https") or not u.netloc:
            raise AgentError(f"agent URL {url!r}: expected http://HOST:PORT", kind="usage", exit_code=1)
        self.url = url.rstrip("/")
        if token is None:
            from .local_token import find

            token = find(self.url)
        self.token = token
        self.timeout = timeout
        self._ssl = _tls(ca, cert, key)

    # ---- transport -------------------------------------------------------------------------------

    def _open(
        self,
        method: str,
        path: str,
        body: Mapping[str, Any] | None = None,
        query: Mapping[str, Any] | None = None,
        timeout: float | None = None,
    ) -> Any:
        q = {k: v for k, v in (query or {}).items() if v is not None}
        target = self.url + path + ("?" + urllib.parse.urlencode(q) if q else "")
        data = None if body is None else json.dumps(dict(body)).encode()
        headers = {"Accept": "application/json"}
        if data is not None:
            headers["Content-Type"] = "application/json"
        if self.token:
            headers["Authorization"] = f"Bearer {self.token}"
        return _urlopen(
            self.url, target, method, data, headers, self.timeout if timeout is None else timeout, self._ssl
        )

    @checked()
    def request(
        self, method: str, path: str, body: Mapping[str, Any] | None = None, query: Mapping[str, Any] | None = None
    ) -> Any:
        """Any call of the HTTP API: its JSON answer (None for an empty one); ``query``: the URL's parameters."""
        with self._open(method, path, body, query) as resp:
            raw = resp.read()
        return json.loads(raw) if raw else None

    @checked()
    def get(self, path: str, query: Mapping[str, Any] | None = None) -> Any:
        return self.request("GET", path, query=query)

    @checked()
    def post(self, path: str, body: Mapping[str, Any] | None = None) -> Any:
        return self.request("POST", path, body if body is not None else {})

    # ---- the API ---------------------------------------------------------------------------------

    @checked()
    def info(self) -> dict[str, Any]:
        return dict(self.get("/v1/agent"))

    @checked()
    def devices(self) -> list[dict[str, Any]]:
        return list(self.get("/v1/devices")["devices"])

    @checked()
    def device(self, name: str) -> dict[str, Any]:
        return dict(self.get("/v1/devices/" + urllib.parse.quote(name, safe="")))

    @checked()
    def pending(self) -> dict[str, Any]:
        return dict(self.get("/v1/pending"))

    @checked()
    def reload(self) -> dict[str, Any]:
        return dict(self.post("/v1/reload"))

    @checked()
    def check(self, limit: str | None = None) -> list[dict[str, Any]]:
        return list(self.post("/v1/check", {"limit": limit} if limit else {})["devices"])

    @checked()
    def runs(self) -> list[dict[str, Any]]:
        return list(self.get("/v1/runs")["runs"])

    @checked()
    def run(self, run_id: str) -> dict[str, Any]:
        return dict(self.get("/v1/runs/" + urllib.parse.quote(run_id, safe="")))

    @checked()
    def start_run(
        self,
        *,
        command: Literal["apply", "restore"] = "apply",
        limit: str | None = None,
        recipe: str | None = None,
        files_sha256: str | None = None,
        batch: str | None = None,
        max_failures: str | None = None,
        parallel: int | None = None,
        soak: str | None = None,
        health_interval: str | None = None,
        confirm_within: str | None = None,
        rollback_on_failure: bool | None = None,
        write_all: bool | None = None,
        force_endurance: bool | None = None,
        client: str | None = None,
        allow_unhealthy: bool | None = None,
    ) -> dict[str, Any]:
        """``POST /v1/runs``: its options as the HTTP API takes them (docs/agent.md; None: the agent's default)."""
        options = {
            "command": command,
            "limit": limit,
            "recipe": recipe,
            "files_sha256": files_sha256,
            "batch": batch,
            "max_failures": max_failures,
            "parallel": parallel,
            "soak": soak,
            "health_interval": health_interval,
            "confirm_within": confirm_within,
            "allow_unhealthy": allow_unhealthy,
            "rollback_on_failure": rollback_on_failure,
            "write_all": write_all,
            "force_endurance": force_endurance,
            "client": client,
        }
        return dict(self.post("/v1/runs", {k: v for k, v in options.items() if v is not None}))

    @checked()
    def stream(self, run_id: str, start: int = 0) -> Iterator[dict[str, Any]]:
        """The run's events as they happen, from event ``start``, until ``run-finished``."""
        path = f"/v1/runs/{urllib.parse.quote(run_id, safe='')}/stream"
        with self._open("GET", path, query={"from": start}, timeout=60) as resp:
            for line in resp:
                if line.strip():
                    yield json.loads(line)

    @checked()
    def follow(self, run_id: str, on_event: Callable[[dict[str, Any]], None] | None = None) -> dict[str, Any]:
        """Follow a run to its end (reconnecting where the stream broke); its ``run-finished`` event."""
        import urllib.error

        seen = 0
        while True:
            try:
                for ev in self.stream(run_id, seen):
                    seen = ev["n"] + 1
                    if on_event is not None:
                        on_event(ev)
                    if ev["event"] == "run-finished":
                        return ev
            except (TimeoutError, ConnectionError, urllib.error.URLError) as e:
                if isinstance(e, urllib.error.URLError) and not isinstance(e.reason, (TimeoutError, ConnectionError)):
                    raise AgentError(
                        f"lost the agent at {self.url}: {e.reason}", kind="unreachable", exit_code=EXIT_UNREACHABLE
                    ) from None

    @checked()
    def apply(
        self,
        *,
        on_event: Callable[[dict[str, Any]], None] | None = None,
        command: Literal["apply", "restore"] = "apply",
        limit: str | None = None,
        recipe: str | None = None,
        files_sha256: str | None = None,
        batch: str | None = None,
        max_failures: str | None = None,
        parallel: int | None = None,
        soak: str | None = None,
        health_interval: str | None = None,
        confirm_within: str | None = None,
        rollback_on_failure: bool | None = None,
        write_all: bool | None = None,
        force_endurance: bool | None = None,
        client: str | None = None,
        allow_unhealthy: bool | None = None,
    ) -> dict[str, Any]:
        """Start a run (its options as ``start_run``'s) and follow it to its end: the ``run-finished`` event
        (``report``, ``exit_code``); ``on_event`` is told each event as it comes."""
        run = self.start_run(
            command=command,
            limit=limit,
            recipe=recipe,
            files_sha256=files_sha256,
            batch=batch,
            max_failures=max_failures,
            parallel=parallel,
            soak=soak,
            health_interval=health_interval,
            confirm_within=confirm_within,
            rollback_on_failure=rollback_on_failure,
            write_all=write_all,
            allow_unhealthy=allow_unhealthy,
            force_endurance=force_endurance,
            client=client,
        )
        return self.follow(run["id"], on_event)

    @checked()
    def confirm(self, run: str | None = None) -> dict[str, Any]:
        if run is None:
            return dict(self.post("/v1/confirm"))
        return dict(self.post(f"/v1/runs/{urllib.parse.quote(run, safe='')}/confirm"))

    @checked()
    def rollback(self, run: str) -> dict[str, Any]:
        return dict(self.post(f"/v1/runs/{urllib.parse.quote(run, safe='')}/rollback"))

    @checked()
    def windows(self) -> list[dict[str, Any]]:
        return list(self.get("/v1/windows")["windows"])

    @checked()
    def events(
        self, *, after: int = 0, limit: int | None = None, device: str | None = None, kind: str | None = None
    ) -> list[dict[str, Any]]:
        return list(self.get("/v1/events", {"after": after, "limit": limit, "device": device, "kind": kind})["events"])

    @checked()
    def ledger(self) -> dict[str, Any]:
        return dict(self.get("/v1/ledger"))

    @checked()
    def status(self) -> dict[str, Any]:
        return dict(self.get("/v1/status"))

    @checked()
    def whoami(self) -> dict[str, Any]:
        """Who the agent takes this client for: user (None with a site token), roles, credential."""
        return dict(self.get("/v1/whoami"))

    @checked()
    def users(self) -> list[dict[str, Any]]:
        return list(self.get("/v1/users")["users"])

    @checked()
    def add_user(
        self,
        user: str,
        roles: list[str],
        *,
        name: str | None = None,
        certificate: dict[str, str] | None = None,
        token: bool | None = None,
    ) -> dict[str, Any]:
        """Add a user (an admin's): ``name`` (printed), ``certificate`` (``{"cn": ...}`` or ``{"sha256": ...}``);
        the answer carries their token (shown once) unless ``token=False``."""
        fields = {"name": name, "certificate": certificate, "token": token}
        return dict(
            self.post("/v1/users", {"user": user, "roles": roles, **{k: v for k, v in fields.items() if v is not None}})
        )

    @checked()
    def change_user(
        self,
        user: str,
        *,
        roles: list[str] | None = None,
        disabled: bool | None = None,
        new_token: bool | None = None,
        name: str | None = None,
        certificate: dict[str, str] | None = None,
    ) -> dict[str, Any]:
        """Change a user (an admin's): ``roles``, ``disabled``, ``new_token`` (the answer carries it, once),
        ``name``, ``certificate``."""
        changes = dict(roles=roles, disabled=disabled, new_token=new_token, name=name, certificate=certificate)
        path = "/v1/users/" + urllib.parse.quote(user, safe="")
        return dict(self.post(path, {k: v for k, v in changes.items() if v is not None}))

    @checked()
    def metrics(self) -> str:
        with self._open("GET", "/metrics") as resp:
            return str(resp.read().decode())


def _urlopen(
    agent: str,
    target: str,
    method: str,
    data: bytes | None,
    headers: dict[str, str],
    timeout: float,
    context: ssl.SSLContext | None,
) -> Any:
    """The agent's answer to one request (its response, open); its refusal or unreachability as AgentError."""
    import urllib.error
    import urllib.request

    try:
        return urllib.request.urlopen(
            urllib.request.Request(target, data=data, headers=headers, method=method), timeout=timeout, context=context
        )
    except urllib.error.HTTPError as e:
        raise _refusal(e) from None
    except (urllib.error.URLError, OSError) as e:
        why = getattr(e, "reason", e)
        raise AgentError(
            f"cannot reach the agent at {agent}: {why}", kind="unreachable", exit_code=EXIT_UNREACHABLE
        ) from None


def _refusal(e: urllib.error.HTTPError) -> AgentError:
    try:
        body = json.loads(e.read() or b"{}")
        err = body["error"]
        return AgentError(
            str(err["message"]),
            kind=str(err.get("kind", "internal")),
            exit_code=int(err.get("exit_code", 4)),
            diagnostics=err.get("diagnostics") or (),
        )
    except (ValueError, KeyError, TypeError):
        return AgentError(f"the agent answered HTTP {e.code} {e.reason}", kind="internal", exit_code=4)


def _tls(ca: str | None, cert: str | None, key: str | None) -> ssl.SSLContext | None:
    """The client's TLS context: the agent's own CA (a gateway's certificate is rarely one the system trusts) and who
    we are by certificate (the agent's users file maps it to a user); None: the system's defaults."""
    if ca is None and cert is None:
        return None
    import ssl

    context = None
    if ca is not None:
        try:
            context = ssl.create_default_context(cafile=ca)
        except (OSError, ssl.SSLError) as e:
            raise AgentError(
                f"agent CA file {ca}: cannot load it: {getattr(e, 'strerror', None) or e}", kind="usage", exit_code=1
            ) from None
    if cert is not None:
        context = context or ssl.create_default_context()
        try:
            context.load_cert_chain(cert, key)
        except (OSError, ssl.SSLError) as e:
            raise AgentError(
                f"client certificate {cert}: cannot load it: {getattr(e, 'strerror', None) or e}",
                kind="usage",
                exit_code=1,
            ) from None
    return context
