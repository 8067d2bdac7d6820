"""Change control on the command line: ``approve``, ``sign``, ``verify``, and ``plan --out``'s change options."""

from __future__ import annotations

import functools
import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import click

from ..errors import EXIT_INVALID, EXIT_OK, UsageError
from .base import echo, safe, stdin_is_terminal

if TYPE_CHECKING:
    from ..api import Recipe
    from ..change.signature import Signer
    from ..change.signers import AllowedSigners


@dataclass(frozen=True)
class ChangeOptions:
    reason: str | None = None
    ticket: str | None = None
    key: str | None = None
    signer: str | None = None
    policy: str | None = None

    @property
    def given(self) -> bool:
        return any((self.reason, self.ticket, self.key, self.signer))


def change_options(f: Callable[..., Any]) -> Callable[..., Any]:
    """``--reason``, ``--ticket``, ``--sign-key``, ``--signer`` for ``plan --out``, handed over as one ``change``."""

    @functools.wraps(f)
    def wrapped(*args: Any, **kw: Any) -> Any:
        kw["change"] = ChangeOptions(
            kw.pop("reason"), kw.pop("ticket"), kw.pop("sign_key"), kw.pop("signer"), kw.pop("policy")
        )
        return f(*args, **kw)

    opts = [
        click.option(
            "--reason",
            metavar="TEXT",
            help="with --out: why this change (recorded in the plan, covered by "
            "its signatures; a site policy can require it)",
        ),
        click.option("--ticket", metavar="ID", help="with --out: the change ticket (a site policy can require it)"),
        click.option(
            "--sign-key",
            type=click.Path(dir_okay=False),
            metavar="KEY",
            help="with --out: sign the plan as its author (an SSH or Ed25519 private key; a public key "
            "KEY.pub signs through ssh-keygen and your ssh-agent)",
        ),
        click.option(
            "--signer",
            metavar="NAME",
            help="the name you sign as (default: the name allowed_signers gives the key, else your user name)",
        ),
        click.option(
            "--policy",
            type=click.Path(dir_okay=False),
            metavar="INVENTORY",
            help="the site's change-control policy, for its allowed_signers (default: DEPLOYER_POLICY)",
        ),
    ]
    out: Callable[..., Any] = wrapped
    for opt in reversed(opts):
        out = opt(out)
    return out


def open_key(path: str) -> Signer:
    """The signing key; an encrypted one's passphrase asked on the terminal."""
    from ..change.signature import NeedsPassphrase, signer_of

    try:
        return signer_of(path)
    except NeedsPassphrase:
        if not stdin_is_terminal():  # Windows: NUL is a tty to isatty
            raise
    phrase = click.prompt(f"passphrase for {path}", hide_input=True, err=True)
    return signer_of(path, phrase.encode())


def _signers(policy_path: str | None, allowed: str | None = None) -> AllowedSigners | None:
    from ..change import load_signers, policy

    if allowed:
        return load_signers(allowed)
    pol = policy.site(policy_path)
    return pol.signers if pol is not None else None


def signer_name(key: Signer, given: str | None, allowed: AllowedSigners | None) -> str:
    """``--signer``, else the one plain name allowed_signers lists the key for (the user's name where it lists several
    and that is one of them; else UsageError: which one is for the signer to say), else the user's name."""
    from ..change.signature import default_signer

    if given:
        return given
    names = sorted(set(allowed.principals_of(key.public_blob()))) if allowed is not None else []
    if len(names) == 1:
        return names[0]
    me = default_signer()
    if names and me not in names:  # signed as the user's name, the signature could never hold
        raise UsageError(
            f"allowed_signers lists the key for {', '.join(names)}: say which you sign as with --signer NAME"
        )
    return me


def stamped(
    data: dict[str, Any], change: ChangeOptions, rec: Recipe | None, files: Sequence[tuple[str, str | None]] = ()
) -> dict[str, Any]:
    """``plan --out``'s document with its ``change`` member (and the author's signature with ``--sign-key``). Its
    inputs: ``rec``'s recipe and profile files, else ``files`` (kind, path): a fleet's recipes, profiles, inventory."""
    from ..api.commands import user_name
    from ..change import digest, sign
    from ..change.files import change_member, input_record

    if rec is not None:
        files = [("recipe", rec.path), ("profile", rec.profile.source)]
    inputs = [input_record(kind, path) for kind, path in dict.fromkeys(files) if path and os.path.isfile(path)]
    key = open_key(change.key) if change.key else None
    author = signer_name(key, change.signer, _signers(change.policy)) if key is not None else user_name()
    doc = {
        **{k: v for k, v in data.items() if k != "signatures"},
        "change": change_member(author, reason=change.reason, ticket=change.ticket, inputs=inputs),
    }
    if key is not None:
        doc["signatures"] = [sign(digest(doc), author, "authored", key)]
    return doc


# ---- commands ---------------------------------------------------------------------------------------


def _key_options(f: Callable[..., Any]) -> Callable[..., Any]:
    opts = [
        click.option(
            "--key",
            type=click.Path(dir_okay=False),
            metavar="KEY",
            help="sign with this key: an SSH private key (OpenSSH format; Ed25519, ECDSA, RSA) or an "
            "Ed25519 PEM key; a public key KEY.pub signs through ssh-keygen (ssh-agent, tokens)",
        ),
        click.option(
            "--signer",
            metavar="NAME",
            help="the name you sign as, as allowed_signers lists it (default: "
            "the one name it gives the key, else your user name)",
        ),
        click.option(
            "--statement-out",
            type=click.Path(dir_okay=False),
            metavar="FILE",
            help="only write the statement to sign (then: ssh-keygen -Y sign -f KEY -n deployer FILE)",
        ),
        click.option(
            "--statement",
            type=click.Path(dir_okay=False, exists=True),
            metavar="FILE",
            help="a statement written by --statement-out, signed by ssh-keygen: give --signature too",
        ),
        click.option(
            "--signature",
            type=click.Path(dir_okay=False, exists=True),
            metavar="FILE.sig",
            help="ssh-keygen -Y sign's signature of --statement",
        ),
        click.option(
            "--policy",
            type=click.Path(dir_okay=False),
            metavar="INVENTORY",
            help="the site's change-control policy (default: DEPLOYER_POLICY): its allowed_signers and "
            "what the plan still lacks",
        ),
        click.option(
            "--state-dir",
            default=".deployer",
            show_default=True,
            type=click.Path(file_okay=False),
            help="where the audit trail is (STATE/audit), unless the policy names its folder",
        ),
    ]
    for opt in reversed(opts):
        f = opt(f)
    return f


@click.command()
@click.argument("plan", type=click.Path(dir_okay=False, exists=True))
@_key_options
def approve(plan: str, **kw: Any) -> int:
    """Approve a saved plan: an `approved` signature over its digest, added to PLAN.

    Refused for the plan's author (four eyes), by name or by the key of their signature, and for a second approval
    by the same signer or key. Says what the plan still lacks under the site policy."""
    return _sign(plan, "approved", **kw)


@click.command()
@click.argument("file", type=click.Path(dir_okay=False, exists=True))
@click.option(
    "--meaning", type=click.Choice(["authored", "reviewed", "approved"]), required=True, help="what the signature means"
)
@_key_options
def sign(file: str, meaning: str, **kw: Any) -> int:
    """Sign a saved plan (into its signatures) or a recipe or profile (into FILE.signatures.json)."""
    return _sign(file, meaning, **kw)


def _sign(
    path: str,
    meaning: str,
    *,
    key: str | None,
    signer: str | None,
    statement_out: str | None,
    statement: str | None,
    signature: str | None,
    policy: str | None,
    state_dir: str,
) -> int:
    from ..audit import commands
    from ..change.check import same_person
    from ..change.files import Signed
    from ..change.signature import statement as make_statement
    from ..change.signature import statement_bytes

    target = Signed(path)
    if target.plan is not None:  # a signature says a plan was read: it is one apply can run (as validate checks it)
        from ..api.commands import validate_file

        validate_file(path)
    allowed = _signers(policy)
    if sum(x is not None for x in (key, statement_out, statement)) != 1 or (statement is None) != (signature is None):
        raise UsageError("give --key KEY, or --statement-out FILE, or --statement FILE with --signature FILE.sig")
    k = None
    if statement is not None and signature is not None:
        entry = _external(statement, signature, target.digest)
        name = entry["signer"]
        if entry["meaning"] != meaning:
            raise UsageError(f"--statement {statement} says {entry['meaning']}, not {meaning}")
    else:
        k = open_key(key) if key is not None else None
        name = signer_name(k, signer, allowed) if k is not None else (signer or _default())
        if k is None and signer is None and allowed is not None and not allowed.knows(name):
            # the statement names who signs it: as the user's name, unknown to the site, it could never hold
            raise UsageError(f"{allowed.path} names nobody {name}: say who signs the statement with --signer NAME")
        if statement_out is not None:
            st = make_statement(target.digest, name, meaning)
            from ..api.commands import write_output

            write_output(statement_out, statement_bytes(st), what="the statement")
            echo(
                f"statement written to {safe(statement_out)}; sign it with:\n  ssh-keygen -Y sign -f KEY -n deployer "
                f"{safe(statement_out)}\nthen: deployer {'approve' if meaning == 'approved' else 'sign'} "
                f"{safe(path)} --statement {safe(statement_out)} --signature {safe(statement_out)}.sig"
            )
            return EXIT_OK
        entry = None
    why = _refusal(target, name, meaning)
    if why is None and meaning == "approved":
        why = same_person(target.signatures, target.author, name, _key_of(entry, k), target.digest, allowed)
    if why is not None:
        for what in commands.refused(
            event="approve-refused",
            path=path,
            digest=target.digest,
            user=name,
            why=why,
            state_dir=state_dir,
            policy_path=policy,
        ):
            echo(f"not recorded: {safe(what)}", err=True)
        raise UsageError(f"{path}: {why}; nothing was signed")
    if entry is None:
        from ..change import sign as make

        assert k is not None
        entry = make(target.digest, name, meaning, k)
    written = target.add(entry)
    echo(
        f"{entry['meaning']} by {safe(name)} at {entry['time']}: signature over {target.digest} added to "
        f"{safe(written)}"
    )
    for what in commands.signed(
        path=path, digest=target.digest, entry=entry, author=target.author, state_dir=state_dir, policy_path=policy
    ):
        echo(f"not recorded: {safe(what)}", err=True)
    _lacks(target.path, policy)
    return EXIT_OK


def _key_of(entry: dict[str, str] | None, key: Any) -> str:
    """The fingerprint of the key an approval is (or was, by hand) made with."""
    from ..change import sshsig

    blob = sshsig.parse(entry["signature"]).public_key if entry is not None else key.public_blob()
    return sshsig.fingerprint(blob)


def _default() -> str:
    from ..change.signature import default_signer

    return default_signer()


def _refusal(target: Any, name: str, meaning: str) -> str | None:
    """Four eyes: the author never approves their own plan; nobody signs the same meaning twice."""
    if meaning == "approved" and target.author is not None and name == target.author:
        return f"{name} is the plan's author: an author cannot approve their own change"
    if any(
        isinstance(s, dict)
        and s.get("signer") == name
        and s.get("meaning") == meaning
        and s.get("digest") == target.digest
        for s in target.signatures
    ):
        return f"{name} has signed it as {meaning} already"
    return None


def _external(statement: str, signature: str, digest: str) -> dict[str, str]:
    """A statement and ssh-keygen's signature of it, as an entry; the statement must be this file's."""
    import json

    from ..change import sshsig
    from ..change.signature import STATEMENT, entry_of, statement_bytes

    try:
        with open(statement, "rb") as f:
            raw = f.read(65536)
        st = json.loads(raw)
        with open(signature, encoding="ascii") as f:
            armor = f.read(65536)
    except (OSError, ValueError) as e:
        raise UsageError(f"--statement {statement} --signature {signature}: cannot read them: {e}") from None
    if not isinstance(st, dict) or st.get("schema") != STATEMENT or statement_bytes(st) != raw:
        raise UsageError(f"--statement {statement}: not a statement written by --statement-out")
    if st.get("digest") != digest:
        raise UsageError(f"--statement {statement} is for other content ({st.get('digest')}); this file is {digest}")
    try:
        sshsig.parse(armor)  # its key is asked of it (a second person's?) before it is added
    except sshsig.SigError as e:
        raise UsageError(f"--signature {signature}: {e}") from None
    return entry_of(st, armor)


def _lacks(path: str, policy_path: str | None) -> None:
    """What a plan still lacks under the site policy, if one is known."""
    from ..change import check_approvals, policy
    from ..change.files import is_plan, read_plan

    with open(path, "rb") as f:
        if not is_plan(f.read(4096)):
            return
    pol = policy.site(policy_path)
    if pol is None:
        return
    missing = check_approvals(read_plan(path), pol)
    if missing:
        echo("the plan still lacks:", err=True)
        for m in missing:
            echo(f"  - {safe(m)}", err=True)
    else:
        echo("the plan has what its policy requires: deployer apply " + safe(path), err=True)


@click.command()
@click.argument("file", type=click.Path(dir_okay=False, exists=True))
@click.option(
    "--allowed-signers",
    type=click.Path(dir_okay=False, exists=True),
    metavar="FILE",
    help="the trusted keys (OpenSSH allowed_signers; default: the policy's)",
)
@click.option(
    "--policy",
    type=click.Path(dir_okay=False),
    metavar="INVENTORY",
    help="the site's change-control policy (default: DEPLOYER_POLICY): also says what a plan lacks",
)
@click.option("--json", "as_json", is_flag=True, help="print what was found as JSON")
def verify(file: str, allowed_signers: str | None, policy: str | None, as_json: bool) -> int:
    """Say who signed FILE (a saved plan, or a recipe or profile with FILE.signatures.json), when, with which
    meaning, and whether each signature still holds. Exit 0 when every one holds (and a plan has what its policy
    requires), else 1."""
    import json

    from ..change import check_approvals
    from ..change import policy as policies
    from ..change import verify as check
    from ..change.files import Signed

    target = Signed(file)
    allowed = _signers(policy, allowed_signers)
    verdicts = [check(e, target.digest, allowed) for e in target.signatures]
    pol = policies.site(policy) if target.plan is not None else None
    missing = check_approvals(target.plan, pol) if target.plan is not None and pol is not None else []
    change = (target.plan or {}).get("change") or {}
    ok = bool(verdicts) and all(v.holds for v in verdicts) and not missing
    if as_json:
        echo(
            json.dumps(
                {
                    "file": file,
                    "digest": target.digest,
                    "change": change,
                    "signatures": [v.to_json() for v in verdicts],
                    "missing": missing,
                    "holds": ok,
                },
                indent=2,
            )
        )
        return EXIT_OK if ok else EXIT_INVALID
    echo(f"{safe(file)}: {target.digest}")
    if isinstance(change, dict) and change:
        said = [f"{k} {safe(change[k])}" for k in ("author", "time", "reason", "ticket") if change.get(k)]
        echo("change: " + "; ".join(said))
    if not verdicts:
        echo("no signatures")
    for v in verdicts:
        state = "holds" if v.holds else f"does NOT hold: {safe(v.why)}"
        echo(
            f"  {v.meaning:<9} {safe(v.signer)}{f' (attested by {safe(v.attested_by)})' if v.attested_by else ''} "
            f"at {safe(v.time)}: {state}"
        )
    if allowed is None and verdicts:
        echo("no allowed signers (--allowed-signers FILE, or a policy's): nobody vouches for these keys", err=True)
    for m in missing:
        echo(f"lacks: {safe(m)}")
    return EXIT_OK if ok else EXIT_INVALID
