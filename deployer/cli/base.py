"""Command line frame: the click group ``cli``, the entry point ``main`` and the helpers every command shares."""

from __future__ import annotations

import contextlib
import sys
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import click

from ..errors import EXIT_INVALID, DeployerError, InputError, UsageError
from ..limits import LIMITS, Bound
from ..load.messages import printable

if TYPE_CHECKING:
    from collections.abc import Mapping

    from rich.console import Console

    from ..api import Profile, Recipe
    from ..api.commands import DeviceURL, Job


class LazyGroup(click.Group):
    """A group whose commands are imported when one runs (click's documented pattern), not at start-up.

    ``lazy``: command name -> ``"module:object"``. ``--help`` imports every command's module for its
    summary line; those modules import their heavy dependencies inside the commands.
    """

    def __init__(self, *args: Any, lazy: Mapping[str, str] | None = None, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.lazy = dict(lazy or {})

    def list_commands(self, ctx: click.Context) -> list[str]:
        return sorted([*super().list_commands(ctx), *self.lazy])

    def get_command(self, ctx: click.Context, cmd_name: str) -> click.Command | None:
        if cmd_name not in self.lazy:
            return super().get_command(ctx, cmd_name)
        import importlib

        module, _, attr = self.lazy[cmd_name].partition(":")
        command = getattr(importlib.import_module(module), attr)
        if not isinstance(command, click.Command):  # pragma: no cover - a wrong entry in the table below
            raise TypeError(f"{self.lazy[cmd_name]} is not a click command")
        return command

    def resolve_command(
        self, ctx: click.Context, args: list[str]
    ) -> tuple[str | None, click.Command | None, list[str]]:
        try:
            return super().resolve_command(ctx, args)
        except click.UsageError as e:
            import difflib

            # click names the nearest of the commands it has imported, and these are not yet: the nearest said here
            near = difflib.get_close_matches(args[0], self.list_commands(ctx), n=1) if args else []
            if near and str(e.message).startswith("No such command") and "Did you mean" not in e.format_message():
                raise click.UsageError(f"{e.message} Did you mean {near[0]!r}?", ctx) from None
            raise

    def invoke(self, ctx: click.Context) -> Any:
        from ..api.commands import writing_caches  # a command runs (not the group's --help or --version

        # the command line keeps pint's answers on disk; library callers do not write there
        with writing_caches():
            return super().invoke(ctx)


_COMMANDS = {
    "agent": "deployer.cli.agent:agent",
    "apply": "deployer.cli.apply:apply",
    "approve": "deployer.cli.change:approve",
    "audit": "deployer.cli.audit:audit",
    "confirm": "deployer.cli.apply:confirm",
    "demo": "deployer.cli.simulate:demo",
    "diff": "deployer.cli.read:diff",
    "docs": "deployer.cli.files:docs_command",
    "explain": "deployer.cli.files:explain",
    "learned": "deployer.cli.field:learned",
    "plan": "deployer.cli.plan:plan",
    "probe": "deployer.cli.field:probe",
    "profiles": "deployer.cli.profiles:profiles",
    "pull": "deployer.cli.read:pull",
    "report": "deployer.cli.report:report",
    "rollback": "deployer.cli.apply:rollback",
    "scan": "deployer.cli.field:scan",
    "sign": "deployer.cli.change:sign",
    "simulate": "deployer.cli.simulate:simulate",
    "status": "deployer.cli.apply:status",
    "users": "deployer.cli.users:users",
    "validate": "deployer.cli.files:validate",
    "verify": "deployer.cli.change:verify",
}


@click.group(cls=LazyGroup, lazy=_COMMANDS, context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(package_name="modbus-deployer")
def cli() -> None:
    """Deploy parameter sets (recipes) to Modbus devices: plan, apply, verify, report."""


def safe(value: object) -> str:
    """User text (a name, label, value, file name) for a line on the terminal: control characters,
    escape sequences, new lines and bidi overrides shown escaped (``load.messages.printable``)."""
    return printable(str(value))


def echo(message: str = "", *, err: bool = False, nl: bool = True) -> None:
    """``click.echo`` for lines the program made: whatever they quote cannot act on the terminal
    (their own line breaks stay; ``safe`` the user text in them so a name cannot start a line)."""
    click.echo(printable(message, newlines=True), err=err, nl=nl)


def report_input_error(err: InputError, outcome: str = "nothing was sent to any device") -> None:
    for d in err.diagnostics:
        echo(safe(d), err=True)
    n = len(err.diagnostics)
    echo(f"{n} error{'s' if n != 1 else ''}; {outcome}", err=True)


def stdin_is_terminal() -> bool:
    """Whether a person can answer a question on stdin (``is_terminal``)."""
    return is_terminal(sys.stdin)


def is_terminal(stream: Any) -> bool:
    """Whether ``stream`` is a terminal. ``isatty()``, except on Windows, where isatty is true of any character
    device, NUL too (the input of a service, a scheduled task, ``< NUL``, output to ``> NUL``): there only a
    console, which GetConsoleMode knows."""
    try:
        if not stream.isatty():
            return False
        fd = stream.fileno()
    except (AttributeError, ValueError, OSError):
        return False
    if sys.platform == "win32":
        import ctypes
        import msvcrt

        mode = ctypes.c_uint32()
        return bool(ctypes.windll.kernel32.GetConsoleMode(msvcrt.get_osfhandle(fd), ctypes.byref(mode)))
    return True


def console(*, stderr: bool = False) -> Console:
    """stdout (or stderr) console; wide when not a terminal so piped lines are not squeezed. It never
    reads markup and escapes control characters (``text.SafeConsole``): style with ``text.styled``."""
    from .text import SafeConsole  # only commands that print pay for importing rich

    if stderr:
        return SafeConsole(stderr=True)
    return SafeConsole(width=None if is_terminal(sys.stdout) else 200)


def describe(url: DeviceURL) -> str:
    """The URL as users write it."""
    from ..api.commands import describe_url

    return describe_url(url)


def _n(count: int, noun: str) -> str:
    return f"{count} {noun}{'' if count == 1 else 's'}"


def write_page(text: str, path: str) -> None:
    """An HTML page (``--html FILE``), written whole or not at all (``write_atomic``'s rule)."""
    from ..api.commands import write_output as write_atomic

    write_atomic(path, text)


def _output(text: str, path: str | None, summary: str, *, replace: bool | None = None) -> None:
    """``text`` into the file ``path`` (saying ``summary`` on stderr), or onto stdout.

    The file goes through ``write_atomic`` (regular files and new paths only). ``replace``: whether an
    existing file may be replaced; None: only with the command's --force (``force_option``).
    """
    from ..api.commands import write_output as write_atomic

    if path:
        if replace is None:
            replace = bool(click.get_current_context().meta.get("deployer.force"))
        write_atomic(path, text, replace=replace)
        echo(summary, err=True)
    elif is_terminal(sys.stdout):  # a file's text shown: nothing in it acts on the terminal
        echo(text, nl=False)
    else:  # piped into a file or a program: the file's text exactly
        click.echo(text, nl=False)


def _set_force(ctx: click.Context, _param: click.Parameter, value: bool) -> bool:
    ctx.meta["deployer.force"] = value
    return value


# -o FILE of a command that makes a file (import, export): replacing an existing file takes --force
force_option = click.option(
    "--force", is_flag=True, expose_value=False, callback=_set_force, help="overwrite an existing output file"
)


def int_range(bound: Bound) -> click.IntRange:
    """A whole-number option within a bound of ``deployer.LIMITS`` (the API and Ansible check the same)."""
    return click.IntRange(int(bound.low), int(bound.high))


def float_range(bound: Bound) -> click.FloatRange:
    def whole(x: float) -> float:  # "600", not "600.0", in --help
        return int(x) if float(x).is_integer() else x

    return click.FloatRange(min=whole(bound.low), max=whole(bound.high), min_open=bound.low_open)


TIMEOUT = float_range(LIMITS.timeout)
RETRIES = int_range(LIMITS.retries)

_device_options = [
    click.option("--device", "device", metavar="URL", help="device URL (default: the recipe's device.url)"),
    click.option("--unit", type=click.IntRange(0, 247), help="unit id (default: the recipe's, else 1)"),
    click.option("--timeout", type=TIMEOUT, help="seconds per attempt"),
    click.option("--retries", type=RETRIES, help="retries after a timeout or busy answer"),
]


class Duration(click.ParamType[float]):
    """A duration option: ``250ms``, ``30s``, ``5m``, ``1h``; a bare number is seconds. The value is in seconds,
    within ``bound`` (a field of ``deployer.LIMITS``)."""

    name = "duration"

    def __init__(self, bound: Bound | None = None) -> None:
        self.bound = bound

    def convert(self, value: Any, param: click.Parameter | None, ctx: click.Context | None) -> float:
        if isinstance(value, float):
            return value
        from ..load.durations import parse_duration

        try:
            seconds = parse_duration(value)
        except ValueError as e:
            self.fail(str(e), param, ctx)
        why = self.bound.problem(seconds, f"'{value}'") if self.bound is not None else None
        if why is not None:
            self.fail(why, param, ctx)
        return seconds


def device_options(f: Callable[..., Any]) -> Callable[..., Any]:
    for opt in reversed(_device_options):
        f = opt(f)
    return f


LIMIT_HELP = (
    "inventory devices: names, groups and glob patterns, comma-separated (!X excludes); "
    "@REPORT.json = the devices of that report that did not end ok"
)
fleet_option = click.option("--inventory", type=click.Path(dir_okay=False), help="every device of an inventory")
limit_option = click.option("--limit", metavar="SEL", help=LIMIT_HELP)
parallel_option = click.option(
    "--parallel",
    type=int_range(LIMITS.parallel),
    default=8,
    show_default=True,
    help="devices at once (devices on one bus always go one at a time)",
)
# the commands that can run through the site agent (deployer.cli.agentclient talks to it)
_agent_url_option = click.option(
    "--agent",
    "agent_url",
    metavar="URL",
    envvar="DEPLOYER_AGENT",
    help="run through the site agent at URL (deployer agent; env DEPLOYER_AGENT): it owns the devices, executes, "
    "and holds the windows",
)


def _remember(ctx: click.Context, param: click.Parameter, value: str | None) -> None:
    """The agent's token file and CA go to deployer.cli.agentclient through the context, not every signature."""
    if value is not None and param.name:
        ctx.meta["deployer.agent." + param.name] = value


_agent_token_option = click.option(
    "--agent-token-file",
    metavar="FILE",
    type=click.Path(dir_okay=False),
    expose_value=False,
    callback=_remember,
    help="the agent's token or your own (its first line); or env DEPLOYER_AGENT_TOKEN",
)
_agent_ca_option = click.option(
    "--agent-ca",
    metavar="FILE",
    type=click.Path(dir_okay=False),
    expose_value=False,
    callback=_remember,
    envvar="DEPLOYER_AGENT_CA",
    help="CA certificate (PEM) an https:// agent's certificate is checked against",
)
_agent_cert_option = click.option(
    "--agent-cert",
    metavar="FILE",
    type=click.Path(dir_okay=False),
    expose_value=False,
    callback=_remember,
    envvar="DEPLOYER_AGENT_CERT",
    help="your TLS client certificate (PEM, with its key or --agent-key) for an "
    "agent that maps certificates to users (env DEPLOYER_AGENT_CERT)",
)
_agent_key_option = click.option(
    "--agent-key",
    metavar="FILE",
    type=click.Path(dir_okay=False),
    expose_value=False,
    callback=_remember,
    envvar="DEPLOYER_AGENT_KEY",
    help="the client certificate's private key (PEM; env DEPLOYER_AGENT_KEY)",
)


def agent_options(f: Callable[..., Any]) -> Callable[..., Any]:
    """The credentials of an agent's client: token file, CA, client certificate (``agentclient.client``)."""
    return _agent_token_option(_agent_ca_option(_agent_cert_option(_agent_key_option(f))))


def agent_option(f: Callable[..., Any]) -> Callable[..., Any]:
    """``--agent URL`` with ``--agent-token-file``, ``--agent-ca`` and ``--agent-cert/--agent-key``."""
    return _agent_url_option(agent_options(f))


def _target(
    recipe: Recipe, device: str | None, unit: int | None, timeout: float | None, retries: int | None, *, required: bool
) -> tuple[DeviceURL | None, int]:
    """The device URL and unit from the options, else the recipe's; parsed before any I/O."""
    from ..api.commands import device_url  # not the transports: an offline plan does not import pymodbus

    text = device or (recipe.device.url if recipe.device else None)
    u = unit if unit is not None else (recipe.device.unit if recipe.device and recipe.device.unit is not None else 1)
    if text is None:
        if required:
            raise UsageError("no device: pass --device URL or set device.url in the recipe")
        return None, u
    return device_url(text, timeout=timeout, retries=retries), u  # BadURL is a UsageError


def read_device(profile: Profile, names: Sequence[str], url: DeviceURL, unit: int) -> dict[str, tuple[int, ...]] | None:
    """Current values for plan --device, diff and pull; None (after saying why) when unreachable."""
    import asyncio  # not at import: --version and --help need no event loop

    from ..api import TransportError
    from ..api.commands import pull_async

    try:
        return asyncio.run(pull_async(profile, url, unit, names=names))
    except TransportError as e:
        echo(f"error: {safe(e)}", err=True)
        return None


def _unreachable(values: Mapping[str, object]) -> list[str]:
    return [n for n, v in values.items() if isinstance(v, Exception)]


def _fleet(
    rec: Recipe | None, inventory: str, limit: str | None, timeout: float | None, retries: int | None, unit: int | None
) -> list[Job]:
    from ..api.commands import fleet_jobs

    return fleet_jobs(rec, inventory, limit=limit, timeout=timeout, retries=retries, unit=unit)


def recipe_or_inventory(recipe: str | None, inventory: str | None, *, what: str = "RECIPE") -> Recipe | None:
    """The command line's recipe, loaded; None when there is none and the inventory's devices name theirs."""
    from ..api import load_recipe

    if recipe is not None:
        return load_recipe(recipe)
    if inventory is None:
        raise UsageError(f"pass {what}, or --inventory FILE whose devices name their recipes")
    return None


def record_meta(inventory: str | None = None, given: Sequence[str] = ()) -> list[tuple[str, str]]:
    """What the commissioning record says at the top of every page: the inventory's ``meta:`` (site, project,
    customer, line ...), then each ``KEY=VALUE`` of ``given`` (the command line's ``--meta``), which wins."""
    out: dict[str, str] = {}
    if inventory is not None:
        from ..api import load_inventory

        out.update(load_inventory(inventory).meta)
    for item in given:
        key, sep, value = str(item).partition("=")
        if not sep or not key.strip():
            raise UsageError(f"--meta {item!r}: expected KEY=VALUE (e.g. site='Plant 3')")
        out[key.strip()] = value.strip()
    return list(out.items())


@dataclass(frozen=True)
class CliContext:
    """What the command line knows about its own process, handed to every command (``click``'s ``obj``).

    ``argv``: the command as typed (for the journal, reports and pages); ``own_process``: ``main()`` runs as
    the process itself (the ``deployer`` script), not called by a test or a program, so it may tune the
    process (the garbage collector) for a command that ends with it.
    """

    argv: tuple[str, ...] = ()
    own_process: bool = False


def cli_context() -> CliContext:
    """The running command's context (the defaults outside ``main``)."""
    ctx = click.get_current_context(silent=True)
    found = ctx.find_object(CliContext) if ctx is not None else None
    return found if found is not None else CliContext()


def command_line(fallback: str = "") -> str:
    """The command as the user typed it (quoted as a shell would need it), for reports and pages."""
    import shlex

    argv = cli_context().argv
    return shlex.join(["deployer", *argv]) if argv else f"deployer {fallback}".rstrip()


def main(argv: Sequence[str] | None = None) -> None:
    """Entry point: map every user error to its exit code, never a traceback."""
    context = CliContext(tuple(argv) if argv is not None else tuple(sys.argv[1:]), own_process=argv is None)
    if context.own_process:
        _encodable_output()
    try:
        _main(argv, context)
    finally:
        if context.own_process:  # the process itself (not a test calling in): its objects end with it, so the
            import gc  # interpreter's last collection need not walk them (40 ms after a 200-device fleet)

            gc.freeze()


def _encodable_output() -> None:
    """Windows writes to a pipe or file in its ANSI code page (cp1252), which has no place for a profile's
    "Ω" or a name in another script: such a character becomes "?" there rather than a traceback (a console
    and PYTHONUTF8=1 get UTF-8)."""
    for stream in (sys.stdout, sys.stderr):
        encoding = (getattr(stream, "encoding", None) or "").lower().replace("-", "")
        if encoding not in ("utf8", "utf_8") and hasattr(stream, "reconfigure"):
            with contextlib.suppress(ValueError, OSError):
                stream.reconfigure(errors="replace")


def _main(argv: Sequence[str] | None, context: CliContext) -> None:
    try:
        rv = cli.main(args=list(argv) if argv is not None else None, standalone_mode=False, obj=context)
    except click.exceptions.Abort:
        echo("aborted", err=True)
        sys.exit(EXIT_INVALID)
    except click.exceptions.ClickException as e:  # usage errors exit 1 (docs/design.md), not click's 2
        import io

        shown = io.StringIO()  # click quotes the file names and values given: escaped like every message
        e.show(file=shown)
        echo(shown.getvalue(), err=True, nl=False)
        sys.exit(EXIT_INVALID)
    except DeployerError as e:  # each class carries its exit code (deployer/errors.py)
        if isinstance(e, InputError):
            report_input_error(e)
        else:
            echo(f"error: {safe(e)}", err=True)
            for line in getattr(e, "diagnostics", None) or ():  # an agent's answer about its files
                echo(safe(line), err=True)
        sys.exit(e.exit_code)
    except KeyboardInterrupt:
        echo("interrupted", err=True)
        sys.exit(130)
    sys.exit(rv if isinstance(rv, int) else 0)
