"""How deployer's public calls take their arguments, and their blocking twins.

Every error the library raises is a ``DeployerError``, and so is a call it cannot take: a misspelt keyword
(``parallel`` written ``paralel``), a missing or an extra argument raises ``UsageError`` naming it (and the
keyword nearest to a misspelt one), where Python would raise a bare ``TypeError``. ``checked`` wraps a public
function or method for that; ``blocking`` makes the plain function of a coroutine (``deployer.plan`` of
``deployer.aio.plan``).
"""

from __future__ import annotations

import asyncio
import difflib
import functools
import inspect
from collections.abc import Callable, Coroutine, Mapping
from typing import Any, ParamSpec, TypeVar, cast

from .errors import UsageError

P = ParamSpec("P")
T = TypeVar("T")

_NAMED = (inspect.Parameter.POSITIONAL_OR_KEYWORD, inspect.Parameter.KEYWORD_ONLY)


def call_problem(
    name: str,
    sig: inspect.Signature,
    args: tuple[Any, ...],
    kwargs: Mapping[str, Any],
    hints: Mapping[str, str] | None = None,
) -> str | None:
    """What is wrong with calling ``name`` (a function of signature ``sig``) so, or None when nothing is.

    ``hints``: keyword -> what to say when it is given and the function has no such argument (a keyword an
    earlier release took)."""
    params = sig.parameters
    takes_any = any(p.kind is inspect.Parameter.VAR_KEYWORD for p in params.values())
    named = [n for n, p in params.items() if p.kind in _NAMED and n != "self"]
    if not takes_any:
        for key in kwargs:
            if key in params and params[key].kind in _NAMED:
                continue
            if hints and key in hints:
                return f"{name}() has no argument {key!r}: {hints[key]}"
            near = difflib.get_close_matches(key, named, n=1, cutoff=0.6)
            if near:
                return f"{name}() has no argument {key!r}; did you mean {near[0]!r}?"
            return f"{name}() has no argument {key!r}; it takes {_names(named)}"
    try:
        sig.bind(*args, **kwargs)
    except TypeError as e:
        return _bind_problem(name, sig, args, kwargs) or f"{name}(): {e}"
    return None


def _names(names: list[str]) -> str:
    if not names:
        return "no arguments"
    return ", ".join(names[:-1]) + (" and " if len(names) > 1 else "") + names[-1]


def _bind_problem(name: str, sig: inspect.Signature, args: tuple[Any, ...], kwargs: Mapping[str, Any]) -> str | None:
    params = [p for p in sig.parameters.values()]
    positional = [
        p for p in params if p.kind in (inspect.Parameter.POSITIONAL_ONLY, inspect.Parameter.POSITIONAL_OR_KEYWORD)
    ]
    own = 1 if positional and positional[0].name == "self" else 0  # a method: its instance is no argument
    if not any(p.kind is inspect.Parameter.VAR_POSITIONAL for p in params) and len(args) > len(positional):
        shown = [p.name for p in positional[own:]]
        return (
            f"{name}() takes {len(shown)} positional argument{'s' if len(shown) != 1 else ''} "
            f"({_names(shown)}), got {len(args) - own}; pass the others by keyword"
        )
    twice = [p.name for p in positional[: len(args)] if p.name in kwargs]
    if twice:
        return f"{name}() got {twice[0]!r} twice: by position and by keyword"
    given = {p.name for p in positional[: len(args)]} | set(kwargs)
    missing = [
        p.name
        for p in params
        if p.default is inspect.Parameter.empty
        and p.name not in given
        and p.kind not in (inspect.Parameter.VAR_POSITIONAL, inspect.Parameter.VAR_KEYWORD)
    ]
    if missing:
        return f"{name}() needs {_names([repr(m) for m in missing])}"
    return None


def checked(
    name: str | None = None, *, hints: Mapping[str, str] | None = None
) -> Callable[[Callable[P, T]], Callable[P, T]]:
    """A decorator: the function (or coroutine function, or method) refuses a call it cannot take with a
    UsageError saying why, before it runs. ``name``: how messages call it (``deployer.apply``; default its
    qualified name); ``hints``: see ``call_problem``."""

    def wrap(f: Callable[P, T]) -> Callable[P, T]:
        sig = inspect.signature(f)
        said = name or f.__qualname__

        if inspect.iscoroutinefunction(f):

            @functools.wraps(f)
            async def checked_coroutine(*args: Any, **kwargs: Any) -> Any:
                why = call_problem(said, sig, args, kwargs, hints)
                if why is not None:
                    raise UsageError(why)
                return await f(*args, **kwargs)

            return cast(Callable[P, T], checked_coroutine)

        @functools.wraps(f)
        def checked_call(*args: P.args, **kwargs: P.kwargs) -> T:
            why = call_problem(said, sig, args, kwargs, hints)
            if why is not None:
                raise UsageError(why)
            return f(*args, **kwargs)

        return checked_call

    return wrap


def blocking(
    name: str, twin: str, *, hints: Mapping[str, str] | None = None
) -> Callable[[Callable[P, Coroutine[Any, Any, T]]], Callable[P, T]]:
    """Makes the plain function of a coroutine function: it runs the coroutine in an event loop of its own.
    Called inside a running event loop (where it would block that loop) it says to await ``twin`` instead.
    ``name``: how messages call it; its arguments are checked as ``checked`` does. (A decorator factory: type
    checkers keep the overloads of the coroutine function through it.)"""

    def wrap(f: Callable[P, Coroutine[Any, Any, T]]) -> Callable[P, T]:
        sig = inspect.signature(f)

        @functools.wraps(f)
        def call(*args: P.args, **kwargs: P.kwargs) -> T:
            why = call_problem(name, sig, args, kwargs, hints)
            if why is not None:
                raise UsageError(why)
            return in_own_loop(lambda: f(*args, **kwargs), name, twin)

        return call

    return wrap


def in_own_loop(coro: Callable[[], Coroutine[Any, Any, T]], name: str, twin: str | None = None) -> T:
    """The result of the coroutine ``coro()`` makes, run in an event loop of its own; inside a running event loop
    (which it would block) a UsageError that says so, and to await ``twin`` instead."""
    try:
        asyncio.get_running_loop()
    except RuntimeError:
        return asyncio.run(coro())
    raise UsageError(f"{name}() cannot run inside a running event loop" + (f"; await {twin}()" if twin else ""))
