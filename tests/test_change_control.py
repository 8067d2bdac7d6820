"""Change control (docs/change-control.md): plans with a reason, four-eyes approvals, SSH signatures that
ssh-keygen reads and writes, the site policy, and the printed record's signatures.

The command line runs as real processes (``python -m deployer``) against a simulator on 127.0.0.1; what the
device received is its request log. ssh-keygen (OpenSSH) is the implementation we did not write.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from deployer.change import check_approvals, digest, load_policy, load_signers, sign, signer_of, verify
from deployer.change.signature import statement, statement_bytes
from deployer.errors import InputError
from deployer.profile import load_profile
from deployer.testing.simulator import Simulator, SimulatorThread
from tests.agent_helpers import PROFILE, RECIPE

SSH_KEYGEN = shutil.which("ssh-keygen")
needs_ssh = pytest.mark.skipif(
    SSH_KEYGEN is None, reason="ssh-keygen is not installed (apt-get install openssh-client)"
)


def run(tmp: Path, *args: str, env: dict[str, str] | None = None) -> subprocess.CompletedProcess[str]:
    """``deployer ARGS`` as its own process, in ``tmp``."""
    return subprocess.run(
        [sys.executable, "-m", "deployer", *args],
        cwd=tmp,
        capture_output=True,
        text=True,
        timeout=120,
        env={**os.environ, "DEPLOYER_POLICY": "", **(env or {})},
    )


def keygen(tmp: Path, name: str, kind: str = "ed25519") -> Path:
    """A key pair made by ssh-keygen, as a person has one."""
    assert SSH_KEYGEN is not None
    key = tmp / name
    subprocess.run([SSH_KEYGEN, "-q", "-t", kind, "-N", "", "-C", name, "-f", str(key)], check=True)
    return key


def pykeygen(tmp: Path, name: str) -> Path:
    """An Ed25519 key pair in OpenSSH's formats, made by pyca's cryptography: where no ssh-keygen is (Windows)."""
    from cryptography.hazmat.primitives import serialization
    from cryptography.hazmat.primitives.asymmetric import ed25519

    key = ed25519.Ed25519PrivateKey.generate()
    (tmp / name).write_bytes(
        key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.OpenSSH, serialization.NoEncryption())
    )
    pub = key.public_key().public_bytes(serialization.Encoding.OpenSSH, serialization.PublicFormat.OpenSSH)
    (tmp / f"{name}.pub").write_bytes(pub + f" {name}\n".encode())
    return tmp / name


def allowed(tmp: Path, *names: str, extra: str = "") -> Path:
    lines = []
    for n in names:
        kind, b64 = (tmp / f"{n}.pub").read_text().split()[:2]
        lines.append(f"{n} {kind} {b64}")
    path = tmp / "allowed_signers"
    path.write_text("\n".join(lines) + "\n" + extra)
    return path


@pytest.fixture
def sim(tmp_path: Path) -> Iterator[Simulator]:
    (tmp_path / "drive.yaml").write_text(PROFILE)
    (tmp_path / "r.yaml").write_text(RECIPE)
    with SimulatorThread(load_profile(str(tmp_path / "drive.yaml"))) as s:
        yield s


def site(tmp: Path, url: str, rule: str = "{approvals: 2, reason: true}") -> Path:
    inv = tmp / "site.yaml"
    inv.write_text(f"""change_control:
  allowed_signers: allowed_signers
  groups:
    line: {rule}
devices:
  press: {{url: "{url}", recipe: r.yaml, groups: [line]}}
""")
    return inv


def accel_changed(plan: dict[str, Any]) -> None:
    """A saved plan's accel 2.1 s instead of 2 s, consistently (its parameter and its write step): the plan is
    valid, just not the one approved."""
    accel = next(p for p in plan["parameters"] if p["name"] == "accel")
    accel["desired"], accel["desired_raw"] = "2.1 s", [21]
    step = next(s for s in plan["steps"] if s["kind"] == "write" and "accel" in s["parameters"])
    step["values"][accel["address"] - step["address"]] = 21


def writes(sim: Simulator) -> list[tuple[int, int]]:
    return [(e.function, e.address) for e in sim.log if e.function in (5, 6, 15, 16)]


# ---- ssh-keygen interoperability -------------------------------------------------------------------------


@needs_ssh
@pytest.mark.parametrize("kind", ["ed25519", "ecdsa", "rsa"])
def test_signatures_go_both_ways_with_ssh_keygen(tmp_path: Path, kind: str) -> None:
    assert SSH_KEYGEN is not None
    key = keygen(tmp_path, "alice", kind)
    signers = allowed(tmp_path, "alice")
    d = "sha256:" + "ab" * 32
    # deployer signs, ssh-keygen verifies
    entry = sign(d, "alice", "approved", signer_of(str(key)))
    (tmp_path / "st").write_bytes(statement_bytes(entry))
    (tmp_path / "st.sig").write_text(entry["signature"])
    ok = subprocess.run(
        [
            SSH_KEYGEN,
            "-Y",
            "verify",
            "-f",
            str(signers),
            "-I",
            "alice",
            "-n",
            "deployer",
            "-s",
            str(tmp_path / "st.sig"),
        ],
        stdin=(tmp_path / "st").open("rb"),
        capture_output=True,
    )
    assert ok.returncode == 0, ok.stderr
    # a changed byte of the statement: ssh-keygen refuses it as well
    (tmp_path / "st2").write_bytes(statement_bytes(entry).replace(b"approved", b"reviewed"))
    bad = subprocess.run(
        [
            SSH_KEYGEN,
            "-Y",
            "verify",
            "-f",
            str(signers),
            "-I",
            "alice",
            "-n",
            "deployer",
            "-s",
            str(tmp_path / "st.sig"),
        ],
        stdin=(tmp_path / "st2").open("rb"),
        capture_output=True,
    )
    assert bad.returncode != 0
    # ssh-keygen signs, deployer verifies
    st = statement(d, "alice", "reviewed")
    (tmp_path / "m").write_bytes(statement_bytes(st))
    subprocess.run([SSH_KEYGEN, "-Y", "sign", "-q", "-f", str(key), "-n", "deployer", str(tmp_path / "m")], check=True)
    theirs = {**st, "format": "sshsig", "namespace": "deployer", "signature": (tmp_path / "m.sig").read_text()}
    v = verify(theirs, d, load_signers(str(signers)))
    assert v.holds and (v.signer, v.meaning) == ("alice", "reviewed"), v.why
    # the same signature over other content, or claiming another signer, fails
    assert "other content" in verify(theirs, "sha256:" + "cd" * 32, load_signers(str(signers))).why
    assert not verify({**theirs, "signer": "mallory"}, d, load_signers(str(signers))).holds


@needs_ssh
def test_a_changed_byte_in_the_plan_fails_verification(tmp_path: Path, sim: Simulator) -> None:
    keygen(tmp_path, "alice")
    allowed(tmp_path, "alice")
    r = run(
        tmp_path,
        "plan",
        "r.yaml",
        "--device",
        sim.url,
        "--out",
        "p.json",
        "--reason",
        "new ramps",
        "--sign-key",
        "alice",
        "--signer",
        "alice",
    )
    assert r.returncode == 0, r.stderr
    v = run(tmp_path, "verify", "p.json", "--allowed-signers", "allowed_signers")
    assert v.returncode == 0 and "authored  alice" in v.stdout and ": holds" in v.stdout, v.stdout + v.stderr
    text = (tmp_path / "p.json").read_text()
    (tmp_path / "p.json").write_text(text.replace('"new ramps"', '"new rampS"', 1))  # one byte
    v = run(tmp_path, "verify", "p.json", "--allowed-signers", "allowed_signers")
    assert v.returncode == 1 and "does NOT hold: it was made over other content" in v.stdout, v.stdout


# ---- four eyes, end to end -----------------------------------------------------------------------------------


@needs_ssh
def test_an_unapproved_plan_is_refused_with_nothing_sent_and_two_approvals_let_it_run(
    tmp_path: Path, sim: Simulator
) -> None:
    for n in ("alice", "bob", "carol", "mallory"):
        keygen(tmp_path, n)
    allowed(tmp_path, "alice", "bob", "carol")  # mallory's key is nobody's
    policy = str(site(tmp_path, sim.url))
    made = run(
        tmp_path,
        "plan",
        "r.yaml",
        "--device",
        sim.url,
        "--out",
        "p.json",
        "--reason",
        "faster ramps",
        "--ticket",
        "CHG-1042",
        "--sign-key",
        "alice",
        "--policy",
        policy,
    )
    assert made.returncode == 0, made.stderr
    doc = json.loads((tmp_path / "p.json").read_text())
    assert doc["change"]["author"] == "alice"  # the name allowed_signers gives the key
    assert doc["change"]["reason"] == "faster ramps" and doc["change"]["ticket"] == "CHG-1042"
    assert [i["kind"] for i in doc["change"]["inputs"]] == ["recipe", "profile"]
    sim.log.clear()

    refused = run(tmp_path, "apply", "p.json", "--yes", "--policy", policy)
    assert refused.returncode == 1 and "nothing was sent" in refused.stderr
    assert "2 approvals by distinct users other than the author alice (none so far)" in refused.stderr
    assert sim.log == []  # not a byte: no connection was even opened

    self_ = run(tmp_path, "approve", "p.json", "--key", "alice", "--policy", policy)
    assert self_.returncode == 1 and "author cannot approve their own change" in self_.stderr
    forged = run(tmp_path, "approve", "p.json", "--key", "mallory", "--signer", "carol", "--policy", policy)
    assert forged.returncode == 0  # written, but worth nothing: the key is not carol's
    assert run(tmp_path, "apply", "p.json", "--yes", "--policy", policy).returncode == 1
    doc = json.loads((tmp_path / "p.json").read_text())
    doc["signatures"] = [s for s in doc["signatures"] if s["signer"] != "carol"]
    (tmp_path / "p.json").write_text(json.dumps(doc, indent=2))

    bob = run(tmp_path, "approve", "p.json", "--key", "bob", "--policy", policy)
    assert bob.returncode == 0 and "1 so far: bob" in bob.stderr
    assert run(tmp_path, "approve", "p.json", "--key", "bob", "--policy", policy).returncode == 1  # bob twice
    one = run(tmp_path, "apply", "p.json", "--yes", "--policy", policy)
    assert one.returncode == 1 and "(1 so far: bob)" in one.stderr and sim.log == []

    carol = run(tmp_path, "approve", "p.json", "--key", "carol", "--policy", policy)
    assert carol.returncode == 0 and "has what its policy requires" in carol.stderr
    # modified after approval: a value in the plan changed by one byte -> refused, nothing sent
    good = (tmp_path / "p.json").read_text()
    doc = json.loads(good)  # accel 2.1 s instead of 2 s, consistently: the plan is valid, just not the approved one
    accel_changed(doc)
    (tmp_path / "p.json").write_text(json.dumps(doc, indent=2))
    changed = run(tmp_path, "apply", "p.json", "--yes", "--policy", policy)
    assert changed.returncode == 1 and "made over other content" in changed.stderr and sim.log == []

    (tmp_path / "p.json").write_text(good)
    ran = run(tmp_path, "apply", "p.json", "--yes", "--policy", policy, "--report", "rep.json")
    assert ran.returncode == 0, ran.stderr
    assert (sim.read("accel"), sim.read("decel")) == ((20,), (30,))  # 2 s, 3 s
    rep = json.loads((tmp_path / "rep.json").read_text())
    change = rep["run"]["change"]
    assert change["digest"] == digest(json.loads(good)) and change["author"] == "alice"
    assert [(s["signer"], s["meaning"], s["holds"]) for s in change["signatures"]] == [
        ("alice", "authored", True),
        ("bob", "approved", True),
        ("carol", "approved", True),
    ]
    trail = [json.loads(x) for x in (tmp_path / ".deployer/audit/trail.jsonl").read_text().splitlines()]
    events = [t["event"] for t in trail]
    assert events.count("apply-refused") == 4 and events[-2:] == ["apply-authorized", "applied"]
    applied = trail[-1]
    assert applied["reason"] == "faster ramps" and applied["plan"] == change["digest"]
    assert {p["name"]: (p["old"], p["new"]) for p in applied["detail"]["parameters"]}["accel"] == ("5 s", "2 s")


def test_one_key_under_two_names_is_one_person(tmp_path: Path, sim: Simulator) -> None:
    """Four eyes are two people: allowed_signers may give a key several names ("alice,alice-ops ..."), but the
    author's key approving under another name, or one key approving twice, is not a second person's approval:
    refused by approve, and not counted by apply when such a signature was added by hand."""
    for n in ("alice", "bob"):
        pykeygen(tmp_path, n)  # no ssh-keygen needed: it runs on Windows too
    allowed(tmp_path, "alice", "bob")
    pub = {n: " ".join((tmp_path / f"{n}.pub").read_text().split()[:2]) for n in ("alice", "bob")}
    with open(tmp_path / "allowed_signers", "a") as f:
        f.write(f"alice-ops {pub['alice']}\nbob-ops {pub['bob']}\n")
    policy = str(site(tmp_path, sim.url, "{approvals: 2}"))

    which = run(
        tmp_path, "plan", "r.yaml", "--device", sim.url, "--out", "p.json", "--sign-key", "alice", "--policy", policy
    )
    assert which.returncode == 1 and "lists the key for alice, alice-ops: say which" in which.stderr
    made = run(
        tmp_path, "plan", "r.yaml", "--device", sim.url, "--out", "p.json", "--sign-key", "alice", "--signer", "alice",
        "--policy", policy,
    )  # fmt: skip
    assert made.returncode == 0, made.stderr
    own = run(tmp_path, "approve", "p.json", "--key", "alice", "--signer", "alice-ops", "--policy", policy)
    assert own.returncode == 1 and "signed the plan as its author alice" in own.stderr
    assert run(tmp_path, "approve", "p.json", "--key", "bob", "--signer", "bob", "--policy", policy).returncode == 0
    twice = run(tmp_path, "approve", "p.json", "--key", "bob", "--signer", "bob-ops", "--policy", policy)
    assert twice.returncode == 1 and "approved it already, as bob: one key is one person" in twice.stderr

    # the same signatures made outside approve (by hand, or an older deployer) hold, and still do not count
    doc = json.loads((tmp_path / "p.json").read_text())
    d = digest(doc)
    doc["signatures"] += [
        sign(d, "alice-ops", "approved", signer_of(str(tmp_path / "alice"))),
        sign(d, "bob-ops", "approved", signer_of(str(tmp_path / "bob"))),
    ]
    (tmp_path / "p.json").write_text(json.dumps(doc, indent=2))
    held = [
        v.signer
        for v in (verify(e, d, load_signers(str(tmp_path / "allowed_signers"))) for e in doc["signatures"])
        if v.holds
    ]
    assert held == ["alice", "bob", "alice-ops", "bob-ops"]
    sim.log.clear()
    refused = run(tmp_path, "apply", "p.json", "--yes", "--policy", policy)
    assert refused.returncode == 1 and "(1 so far: bob; not counted: approved by alice-ops" in refused.stderr
    assert (
        "with the key of the author alice" in refused.stderr and "with the key that approved as bob" in refused.stderr
    )
    assert sim.log == []


@needs_ssh
def test_an_approval_signed_by_hand_names_its_signer_and_one_that_does_not_hold_blocks_nobody(
    tmp_path: Path, sim: Simulator
) -> None:
    assert SSH_KEYGEN is not None
    for n in ("alice", "bob"):
        keygen(tmp_path, n)
    allowed(tmp_path, "alice", "bob")
    policy = str(site(tmp_path, sim.url, "{approvals: 1}"))
    made = run(
        tmp_path, "plan", "r.yaml", "--device", sim.url, "--out", "p.json", "--sign-key", "alice", "--policy", policy
    )
    assert made.returncode == 0, made.stderr
    # the statement names its signer: the user's name, unknown to the site, would make a signature that never holds
    nobody = run(tmp_path, "approve", "p.json", "--statement-out", "st.json", "--policy", policy, env={"USER": "zed"})
    assert (
        nobody.returncode == 1 and "names nobody zed: say who signs the statement with --signer NAME" in nobody.stderr
    )
    (tmp_path / "st.json.sig").write_text("not a signature\n")
    assert (
        run(
            tmp_path, "approve", "p.json", "--statement-out", "st.json", "--signer", "bob", "--policy", policy
        ).returncode
        == 0
    )
    bad = run(tmp_path, "approve", "p.json", "--statement", "st.json", "--signature", "st.json.sig", "--policy", policy)
    assert bad.returncode == 1 and bad.stderr.startswith("error: --signature st.json.sig: not an SSH signature")
    # bob's key signs a statement naming carol (written, but it holds for nobody), then bob approves as bob
    (tmp_path / "st.json.sig").unlink()
    assert (
        run(
            tmp_path, "approve", "p.json", "--statement-out", "st.json", "--signer", "carol", "--policy", policy
        ).returncode
        == 0
    )
    subprocess.run([SSH_KEYGEN, "-Y", "sign", "-q", "-f", "bob", "-n", "deployer", "st.json"], cwd=tmp_path, check=True)
    wrong = run(
        tmp_path, "approve", "p.json", "--statement", "st.json", "--signature", "st.json.sig", "--policy", policy
    )
    assert wrong.returncode == 0 and "not for 'carol'" in wrong.stderr
    bob = run(tmp_path, "approve", "p.json", "--key", "bob", "--policy", policy)  # not "approved it already"
    assert bob.returncode == 0 and "approved by bob" in bob.stdout, bob.stderr
    assert "approval by distinct users" not in bob.stderr and "not for 'carol'" in bob.stderr  # it must go


def test_without_a_policy_a_plan_signed_over_other_content_is_refused(tmp_path: Path, sim: Simulator) -> None:
    """No key is needed to see that a signature covers another digest: refused under any policy or none."""
    assert run(tmp_path, "plan", "r.yaml", "--device", sim.url, "--out", "p.json").returncode == 0
    doc = json.loads((tmp_path / "p.json").read_text())
    doc["signatures"] = [
        {
            **statement("sha256:" + "0" * 64, "bob", "approved"),
            "format": "sshsig",
            "namespace": "deployer",
            "signature": "-----BEGIN SSH SIGNATURE-----\n-----END SSH SIGNATURE-----\n",
        }
    ]
    (tmp_path / "p.json").write_text(json.dumps(doc))
    sim.log.clear()
    r = run(tmp_path, "apply", "p.json", "--yes")
    assert r.returncode == 1 and "the plan changed after it was signed" in r.stderr and sim.log == []


def test_a_recipe_is_refused_where_the_policy_needs_a_plan_and_runs_elsewhere(tmp_path: Path, sim: Simulator) -> None:
    (tmp_path / "allowed_signers").write_text("")
    inv = site(tmp_path, sim.url)
    with inv.open("a") as f:
        f.write('  spare: {url: "tcp://127.0.0.1:1", recipe: r.yaml}\n')
    r = run(tmp_path, "apply", "--inventory", str(inv), "--limit", "press", "--yes")
    assert r.returncode == 1 and "only an approved plan changes it" in r.stderr and writes(sim) == []
    r = run(tmp_path, "apply", "r.yaml", "--device", sim.url, "--yes", env={"DEPLOYER_POLICY": str(inv)})
    assert r.returncode == 1 and "press" not in r.stderr.split("refuses")[0] and writes(sim) == []
    other = tmp_path / "other.yaml"  # a device the policy does not name gets only `require` (nothing here)
    with SimulatorThread(load_profile(str(tmp_path / "drive.yaml"))) as free:
        r = run(tmp_path, "apply", "r.yaml", "--device", free.url, "--yes", env={"DEPLOYER_POLICY": str(inv)})
        assert r.returncode == 0, r.stderr
    assert not other.exists()


# ---- the policy and the trusted keys -------------------------------------------------------------------


def test_a_device_takes_the_strictest_rule_of_its_groups(tmp_path: Path) -> None:
    inv = tmp_path / "site.yaml"
    inv.write_text("""change_control:
  require: {approvals: 1}
  groups:
    a: {approvals: 2}
    b: {reason: true, ticket: true}
devices:
  d1: {url: "tcp://127.0.0.1:5021", groups: [a, b]}
  d2: {url: "tcp://127.0.0.1:5022"}
""")
    pol = load_policy(str(inv))
    assert pol is not None
    r1 = pol.rule_for("tcp://127.0.0.1:5021", 1)
    assert (r1.approvals, r1.reason, r1.ticket) == (2, True, True)
    assert pol.rule_for("tcp://127.0.0.1:5022", 1).approvals == 1
    assert pol.rule_for("tcp://127.0.0.1:5021", 2).approvals == 1  # another unit: another device
    doc = {
        "schema": "deployer.plan/2",
        "device": {"url": "tcp://127.0.0.1:5021", "unit": 1},
        "change": {"author": "alice"},
    }
    missing = check_approvals(doc, pol)
    assert any(m.startswith("a reason") for m in missing) and any(m.startswith("a change ticket") for m in missing)
    assert any("2 approvals by distinct users other than the author alice" in m for m in missing)


def test_a_bad_policy_is_refused_at_its_position(tmp_path: Path) -> None:
    inv = tmp_path / "site.yaml"
    inv.write_text('change_control:\n  require: {approvals: many}\ndevices:\n  d: {url: "tcp://127.0.0.1:1"}\n')
    with pytest.raises(InputError) as e:
        load_policy(str(inv))
    assert e.value.diagnostics[0].line == 2


@needs_ssh
def test_allowed_signers_patterns_namespaces_and_validity(tmp_path: Path) -> None:
    key = keygen(tmp_path, "alice")
    kind, b64 = (tmp_path / "alice.pub").read_text().split()[:2]
    path = tmp_path / "as"
    path.write_text(
        f'# site keys\n*@plant.example,!eve@plant.example namespaces="deployer,file",'
        f'valid-before="20300101Z" {kind} {b64}\n'
        f"ca@plant.example cert-authority {kind} {b64}\n"
    )
    signers = load_signers(str(path))
    assert signers.skipped and "certificates are not supported" in signers.skipped[0]
    d = "sha256:" + "11" * 32
    ok = verify(sign(d, "alice@plant.example", "approved", signer_of(str(key))), d, signers)
    assert ok.holds, ok.why
    assert (
        "not for 'eve@plant.example'"
        in verify(sign(d, "eve@plant.example", "approved", signer_of(str(key))), d, signers).why
    )
    path.write_text(f'alice namespaces="git" {kind} {b64}\n')
    assert (
        "does not allow the namespace deployer"
        in verify(sign(d, "alice", "approved", signer_of(str(key))), d, load_signers(str(path))).why
    )
    path.write_text(f"alice valid-before=20200101 {kind} {b64}\n")
    assert "valid-before" in verify(sign(d, "alice", "approved", signer_of(str(key))), d, load_signers(str(path))).why
    path.write_text(f"alice {kind} {b64}\nbob ssh-ed25519 not-base64!\n")
    with pytest.raises(InputError) as e:
        load_signers(str(path))
    assert e.value.diagnostics[0].line == 2


@needs_ssh
def test_a_key_in_ssh_agent_signs_through_ssh_keygen(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    agent = shutil.which("ssh-agent")
    if agent is None:
        pytest.skip("no ssh-agent")
    key = keygen(tmp_path, "alice")
    sock = tmp_path / "agent.sock"
    proc = subprocess.Popen([agent, "-D", "-a", str(sock)], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        env = {**os.environ, "SSH_AUTH_SOCK": str(sock)}
        from tests.agent_helpers import until

        until(sock.exists, why="ssh-agent's socket")
        subprocess.run(["ssh-add", "-q", str(key)], env=env, check=True, capture_output=True)
        key.unlink()  # only the agent has the private key now
        monkeypatch.setenv("SSH_AUTH_SOCK", str(sock))
        d = "sha256:" + "22" * 32
        entry = sign(d, "alice", "reviewed", signer_of(str(tmp_path / "alice.pub")))
        assert verify(entry, d, load_signers(str(allowed(tmp_path, "alice")))).holds
    finally:
        proc.terminate()
        proc.wait(timeout=10)


# ---- approvals through the agent ----------------------------------------------------------------------------


def _post(url: str, body: object, token: str | None) -> tuple[int, dict[str, object]]:
    import urllib.error
    import urllib.request

    req = urllib.request.Request(
        url + "/v1/approvals",
        data=json.dumps(body).encode(),
        method="POST",
        headers={"Content-Type": "application/json", "Authorization": f"Bearer {token}"},
    )
    try:
        with urllib.request.urlopen(req, timeout=20) as resp:
            return resp.status, json.loads(resp.read())
    except urllib.error.HTTPError as e:
        return e.code, json.loads(e.read())


@needs_ssh
def test_the_agent_takes_a_signed_approval_and_refuses_the_authors_and_an_anonymous_one(
    tmp_path: Path, sim: Simulator
) -> None:
    from tests.agent_helpers import AgentProcess

    for n in ("alice", "bob"):
        keygen(tmp_path, n)
    alice_pub = " ".join((tmp_path / "alice.pub").read_text().split()[:2])
    allowed(tmp_path, "alice", "bob", extra=f"alice-ops {alice_pub}\n")  # one person, two names
    inv = site(tmp_path, sim.url, "{approvals: 1}")
    assert (
        run(
            tmp_path,
            "plan",
            "r.yaml",
            "--device",
            sim.url,
            "--out",
            "p.json",
            "--sign-key",
            "alice",
            "--signer",
            "alice",
            "--policy",
            str(inv),
        ).returncode
        == 0
    )
    doc = json.loads((tmp_path / "p.json").read_text())
    agent = AgentProcess(inv, tmp_path / "state")
    try:
        token = agent.client.token  # the token the agent made: the site's one token, no name (access.py)
        mine = sign(digest(doc), "alice", "approved", signer_of(str(tmp_path / "alice")))
        status, answer = _post(agent.url, {"plan": doc, "signature": mine}, token)
        assert status == 403 and "cannot approve their own change" in str(answer["error"])
        other = sign(digest(doc), "alice-ops", "approved", signer_of(str(tmp_path / "alice")))
        status, answer = _post(agent.url, {"plan": doc, "signature": other}, token)  # the author's key, another name
        assert status == 403 and "signed the plan as its author alice" in str(answer["error"])
        status, answer = _post(agent.url, {"plan": doc}, None)  # no credential at all
        assert status == 401 and "needs a named user" not in str(answer["error"])
        status, answer = _post(agent.url, {"plan": doc}, token)  # nobody named (one token): no attestation
        assert status == 401 and "needs a named user" in str(answer["error"])
        bobs = sign(digest(doc), "bob", "approved", signer_of(str(tmp_path / "bob")))
        status, answer = _post(
            agent.url, {"plan": {**doc, "change": {**doc["change"], "reason": "x"}}, "signature": bobs}, token
        )
        assert status == 422 and "other content" in str(answer["error"])  # bob signed another plan
        status, answer = _post(agent.url, {"plan": doc, "signature": bobs}, token)
        assert status == 200 and answer["missing"] == [], answer
        (tmp_path / "p.json").write_text(json.dumps(answer["plan"], indent=2))
    finally:
        assert agent.terminate() == 0
    assert run(tmp_path, "apply", "p.json", "--yes", "--policy", str(inv)).returncode == 0  # the agent let go
    trail = [json.loads(x) for x in (tmp_path / "state/audit/trail.jsonl").read_text().splitlines()]
    asked = [(t["event"], t["via"]) for t in trail if t["event"] != "drift"]  # its watch records drift too
    assert asked == [("approve-refused", "agent")] * 2 + [("login-refused", "agent")] + [
        ("approve-refused", "agent")
    ] * 2 + [("plan-signed", "agent")]


def test_sign_and_approve_refuse_a_file_that_is_no_plan_apply_can_run(tmp_path: Path) -> None:
    """A signature says a plan was read: `sign` and `approve` check a plan as `validate` does first (nothing signed,
    the errors at their positions), where a reviewer could sign a file that `apply` refuses."""
    key = pykeygen(tmp_path, "bob")
    (tmp_path / "drive.yaml").write_text(PROFILE)
    (tmp_path / "r.yaml").write_text(RECIPE)
    assert run(tmp_path, "plan", "r.yaml", "--out", "p.json").returncode == 0
    doc = json.loads((tmp_path / "p.json").read_text())
    doc["steps"] = "x"
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps(doc, indent=2))
    before = bad.read_text()
    for args in (("sign", "bad.json", "--meaning", "reviewed"), ("approve", "bad.json")):
        r = run(tmp_path, *args, "--key", str(key), "--signer", "bob")
        assert r.returncode == 1 and "bad.json:" in r.stderr and "steps: expected a list" in r.stderr, r.stderr
    assert bad.read_text() == before


@needs_ssh
def test_an_agent_attests_for_its_user_only_with_a_key_trusted_to_attest(tmp_path: Path) -> None:
    from deployer.change import attest, policy
    from deployer.change.signers import parse

    keygen(tmp_path, "alice")
    signers = allowed(tmp_path, "alice")
    (tmp_path / "drive.yaml").write_text(PROFILE)
    (tmp_path / "r.yaml").write_text(RECIPE)
    made = run(tmp_path, "plan", "r.yaml", "--out", "p.json")  # offline: the recipe's values against none read
    assert made.returncode == 0, made.stderr
    doc = json.loads((tmp_path / "p.json").read_text())
    doc["change"] = {**doc["change"], "author": "alice", "reason": "r"}
    pol = policy.Policy(signers=parse(str(signers), signers.read_text()))
    with pytest.raises(attest.Refused) as e:  # what is no plan apply can run is approved by nobody
        attest.approve(
            {**doc, "steps": "x"}, user="dave", entry=None, meaning="approved", policy=pol, key_folder=str(tmp_path)
        )
    assert e.value.status == 422 and "not a saved plan apply can run: steps: expected a list" in str(e.value)
    with pytest.raises(attest.Refused) as e:  # its key is not in allowed_signers yet: the line to add is said
        attest.approve(doc, user="dave", entry=None, meaning="approved", policy=pol, key_folder=str(tmp_path / "ag"))
    line = str(e.value).split(": ", 2)[-1]
    assert e.value.status == 409 and 'namespaces="deployer-attest" ssh-ed25519 ' in line
    text = signers.read_text() + line + "\n"
    pol = policy.Policy(signers=parse(str(signers), text))
    out = attest.approve(doc, user="dave", entry=None, meaning="approved", policy=pol, key_folder=str(tmp_path / "ag"))
    v = verify(out["signature"], digest(doc), pol.signers)
    assert v.holds and v.signer == "dave" and v.attested_by and v.attested_by.startswith("deployer-agent@")
    with pytest.raises(attest.Refused):  # the author, authenticated, still cannot approve
        attest.approve(doc, user="alice", entry=None, meaning="approved", policy=pol, key_folder=str(tmp_path / "ag"))
    # a person's key (no namespaces option written out) cannot attest for somebody else
    forged = sign(digest(doc), "bob", "approved", signer_of(str(tmp_path / "alice")), attested_by="alice")
    assert "does not name the namespace deployer-attest" in verify(forged, digest(doc), pol.signers).why


# ---- the printed record ------------------------------------------------------------------------------------


@needs_ssh
@pytest.mark.skipif(shutil.which("pdftotext") is None, reason="pdftotext (poppler-utils) is not installed")
def test_the_printed_record_and_the_audit_page_carry_the_signatures(tmp_path: Path, sim: Simulator) -> None:
    from tests.test_commissioning import _pdf_text
    from tests.test_pages import CHROMIUM

    if CHROMIUM is None:
        pytest.skip("no Chromium")
    for n in ("alice", "bob", "carol"):
        keygen(tmp_path, n)
    allowed(tmp_path, "alice", "bob", "carol")
    policy = str(site(tmp_path, sim.url, "{approvals: 1, ticket: true}"))
    assert (
        run(
            tmp_path,
            "plan",
            "r.yaml",
            "--device",
            sim.url,
            "--out",
            "p.json",
            "--ticket",
            "CHG-7",
            "--reason",
            "new ramps",
            "--sign-key",
            "alice",
            "--policy",
            policy,
        ).returncode
        == 0
    )
    assert (
        run(tmp_path, "sign", "p.json", "--meaning", "reviewed", "--key", "carol", "--policy", policy).returncode == 0
    )
    assert run(tmp_path, "approve", "p.json", "--key", "bob", "--policy", policy).returncode == 0
    r = run(tmp_path, "apply", "p.json", "--yes", "--policy", policy, "--html", "record.html")
    assert r.returncode == 0, r.stderr
    words = " ".join(_pdf_text(tmp_path / "record.html", tmp_path).split())
    d = digest(json.loads((tmp_path / "p.json").read_text()))
    assert "Change and electronic signatures" in words and d[:40] in words.replace(" ", "")
    for who, meaning in (("alice", "authored"), ("carol", "reviewed"), ("bob", "approved")):
        assert f"{who} {meaning} " in words, words
    assert "author alice" in words and "ticket CHG-7" in words and "reason new ramps" in words
    shown = run(tmp_path, "audit", "show", "--user", "bob", "--html", "audit.html")
    assert shown.returncode == 0 and "plan-signed" in shown.stdout and "apply" not in shown.stdout
    page = " ".join(_pdf_text(tmp_path / "audit.html", tmp_path).split())
    assert "bob approved" in page and "every record holds" in page and "user bob" in page


@needs_ssh
def test_released_inputs_signed_by_hand_with_ssh_keygen(tmp_path: Path, sim: Simulator) -> None:
    """The recipe and profile released by hand (deployer writes the statement, ssh-keygen signs it), a policy that
    requires signed inputs: a recipe applies while its signature holds and is refused, nothing sent, once a byte
    of it changed; a plan records the signatures it was made with."""
    assert SSH_KEYGEN is not None
    key = keygen(tmp_path, "qa")
    allowed(tmp_path, "qa")
    policy = str(site(tmp_path, sim.url, "{signed_inputs: true}"))
    refused = run(tmp_path, "apply", "r.yaml", "--device", sim.url, "--yes", "--policy", policy)
    assert refused.returncode == 1 and "an approved signature of the recipe r.yaml (it carries none)" in refused.stderr
    for f in ("r.yaml", "drive.yaml"):
        st = run(tmp_path, "sign", f, "--meaning", "approved", "--signer", "qa", "--statement-out", f"{f}.st")
        assert st.returncode == 0 and "ssh-keygen -Y sign" in st.stdout
        subprocess.run(
            [SSH_KEYGEN, "-Y", "sign", "-q", "-f", str(key), "-n", "deployer", str(tmp_path / f"{f}.st")], check=True
        )
        added = run(
            tmp_path, "sign", f, "--meaning", "approved", "--statement", f"{f}.st", "--signature", f"{f}.st.sig"
        )
        assert added.returncode == 0 and f"{f}.signatures.json" in added.stdout, added.stderr
    v = run(tmp_path, "verify", "r.yaml", "--policy", policy)
    assert v.returncode == 0 and "approved  qa" in v.stdout
    made = run(tmp_path, "plan", "r.yaml", "--device", sim.url, "--out", "p.json", "--policy", policy)
    assert made.returncode == 0
    inputs = json.loads((tmp_path / "p.json").read_text())["change"]["inputs"]
    assert [(i["kind"], len(i["signatures"])) for i in inputs] == [("recipe", 1), ("profile", 1)]
    assert run(tmp_path, "apply", "p.json", "--yes", "--policy", policy).returncode == 0
    sim.log.clear()
    (tmp_path / "r.yaml").write_text(RECIPE.replace("3000 rpm", "3001 rpm"))
    changed = run(tmp_path, "apply", "r.yaml", "--device", sim.url, "--yes", "--policy", policy)
    assert changed.returncode == 1 and "made over other content" in changed.stderr and sim.log == []


def test_reason_and_ticket_describe_a_saved_plan(tmp_path: Path) -> None:
    r = run(tmp_path, "plan", "r.yaml", "--reason", "x")
    assert r.returncode == 1 and "give --out PLAN.json" in r.stderr
