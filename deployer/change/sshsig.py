"""The SSH signature format (OpenSSH's PROTOCOL.sshsig): what ``ssh-keygen -Y sign`` writes and ``-Y verify``
reads.

Only the wire encoding is here: the signing and verifying are pyca/cryptography's (Ed25519, ECDSA P-256/384/521,
RSA with SHA-512 or SHA-256). A signature over a message ``M`` in a namespace ``N`` signs

    "SSHSIG" string(N) string("") string(HASH) string(HASH(M))

and is kept as ``"SSHSIG" uint32(1) string(publickey) string(N) string("") string(HASH) string(signature)``,
armored between ``-----BEGIN SSH SIGNATURE-----`` and ``-----END SSH SIGNATURE-----`` (base64, 70 columns).
"""

from __future__ import annotations

import base64
import binascii
import hashlib
import struct
from dataclasses import dataclass
from typing import Any

from cryptography.exceptions import InvalidSignature, UnsupportedAlgorithm
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec, ed25519, padding, rsa
from cryptography.hazmat.primitives.asymmetric.utils import decode_dss_signature, encode_dss_signature

MAGIC = b"SSHSIG"
VERSION = 1
BEGIN = "-----BEGIN SSH SIGNATURE-----"
END = "-----END SSH SIGNATURE-----"
HASHES = {"sha512": hashlib.sha512, "sha256": hashlib.sha256}
_CURVES: dict[str, tuple[str, type[ec.EllipticCurve], hashes.HashAlgorithm]] = {
    "ecdsa-sha2-nistp256": ("nistp256", ec.SECP256R1, hashes.SHA256()),
    "ecdsa-sha2-nistp384": ("nistp384", ec.SECP384R1, hashes.SHA384()),
    "ecdsa-sha2-nistp521": ("nistp521", ec.SECP521R1, hashes.SHA512()),
}
MAX_ARMOR = 16384  # an RSA-16384 signature armored is under 6 kB


class SigError(ValueError):
    """A signature that cannot be read, or does not verify: the message says which."""


PublicKey = ed25519.Ed25519PublicKey | ec.EllipticCurvePublicKey | rsa.RSAPublicKey
PrivateKey = ed25519.Ed25519PrivateKey | ec.EllipticCurvePrivateKey | rsa.RSAPrivateKey


# ---- the wire ----------------------------------------------------------------------------------


def _string(data: bytes) -> bytes:
    return struct.pack(">I", len(data)) + data


def _mpint(n: int) -> bytes:
    """RFC 4251 mpint of a non-negative number: big-endian, a leading zero byte when the top bit is set."""
    raw = n.to_bytes((n.bit_length() + 8) // 8, "big") if n else b""
    return _string(raw)


class _Reader:
    def __init__(self, data: bytes) -> None:
        self.data, self.at = data, 0

    def take(self, n: int) -> bytes:
        if n < 0 or self.at + n > len(self.data):
            raise SigError("the signature is cut short")
        out = self.data[self.at : self.at + n]
        self.at += n
        return out

    def uint32(self) -> int:
        return int(struct.unpack(">I", self.take(4))[0])

    def string(self) -> bytes:
        return self.take(self.uint32())

    def mpint(self) -> int:
        raw = self.string()
        if raw and raw[0] & 0x80:
            raise SigError("a negative number in the signature")
        return int.from_bytes(raw, "big")

    def end(self) -> None:
        if self.at != len(self.data):
            raise SigError("trailing bytes after the signature")


# ---- keys ------------------------------------------------------------------------------------------


def key_blob(key: PublicKey) -> bytes:
    """The key's SSH wire form (what an ``allowed_signers`` line and a signature carry, base64 or raw)."""
    text = key.public_bytes(serialization.Encoding.OpenSSH, serialization.PublicFormat.OpenSSH)
    return base64.b64decode(text.split()[1])


def key_line(key: PublicKey) -> str:
    """``ssh-ed25519 AAAA...``: the key as ``authorized_keys`` and ``allowed_signers`` write it."""
    return key.public_bytes(serialization.Encoding.OpenSSH, serialization.PublicFormat.OpenSSH).decode()


def key_type(blob: bytes) -> str:
    try:
        return _Reader(blob).string().decode("ascii")
    except (SigError, UnicodeDecodeError):
        return "?"


def public_from_blob(blob: bytes) -> PublicKey:
    """A key from its wire form; SigError for a type we do not verify (security keys, DSA, certificates)."""
    kind = key_type(blob)
    if kind not in ("ssh-ed25519", "ssh-rsa", *_CURVES):
        raise SigError(f"keys of type {kind} are not supported (Ed25519, ECDSA and RSA are)")
    try:
        key = serialization.load_ssh_public_key(kind.encode() + b" " + base64.b64encode(blob))
    except (ValueError, UnsupportedAlgorithm) as e:
        raise SigError(f"the {kind} key cannot be read: {e}") from None
    if not isinstance(key, ed25519.Ed25519PublicKey | ec.EllipticCurvePublicKey | rsa.RSAPublicKey):
        raise SigError(f"keys of type {kind} are not supported")
    return key


def fingerprint(blob: bytes) -> str:
    """``SHA256:...`` as ``ssh-keygen -l`` shows a key."""
    return "SHA256:" + base64.b64encode(hashlib.sha256(blob).digest()).decode().rstrip("=")


# ---- signing and verifying -------------------------------------------------------------------------


def _signed_data(namespace: str, hash_name: str, message: bytes) -> bytes:
    return (
        MAGIC
        + _string(namespace.encode())
        + _string(b"")
        + _string(hash_name.encode())
        + _string(HASHES[hash_name](message).digest())
    )


def _raw_signature(key: PrivateKey, data: bytes) -> bytes:
    """The SSH signature blob of ``data`` (cryptography signs)."""
    if isinstance(key, ed25519.Ed25519PrivateKey):
        return _string(b"ssh-ed25519") + _string(key.sign(data))
    if isinstance(key, ec.EllipticCurvePrivateKey):
        name = next(n for n, (_, curve, _h) in _CURVES.items() if isinstance(key.curve, curve))
        r, s = decode_dss_signature(key.sign(data, ec.ECDSA(_CURVES[name][2])))
        return _string(name.encode()) + _string(_mpint(r) + _mpint(s))
    return _string(b"rsa-sha2-512") + _string(key.sign(data, padding.PKCS1v15(), hashes.SHA512()))


def sign(key: PrivateKey, message: bytes, namespace: str) -> str:
    """The armored SSH signature of ``message`` in ``namespace`` (SHA-512, as ``ssh-keygen -Y sign``)."""
    blob = (
        MAGIC
        + struct.pack(">I", VERSION)
        + _string(key_blob(key.public_key()))
        + _string(namespace.encode())
        + _string(b"")
        + _string(b"sha512")
        + _string(_raw_signature(key, _signed_data(namespace, "sha512", message)))
    )
    text = base64.b64encode(blob).decode()
    return "\n".join([BEGIN, *(text[i : i + 70] for i in range(0, len(text), 70)), END]) + "\n"


@dataclass(frozen=True)
class SshSig:
    """An armored signature read back: the signer's key (wire form), its namespace, hash and signature blob."""

    public_key: bytes
    namespace: str
    hash_name: str
    signature: bytes


def parse(armor: str) -> SshSig:
    """Read an armored signature; SigError says what is wrong with it."""
    if not isinstance(armor, str) or len(armor) > MAX_ARMOR:
        raise SigError("not an SSH signature (too long, or not text)")
    lines = [ln.strip() for ln in armor.strip().splitlines()]
    if len(lines) < 3 or lines[0] != BEGIN or lines[-1] != END:
        raise SigError(f"not an SSH signature: it must start with {BEGIN} and end with {END}")
    try:
        blob = base64.b64decode("".join(lines[1:-1]), validate=True)
    except (binascii.Error, ValueError):
        raise SigError("the signature's base64 is damaged") from None
    r = _Reader(blob)
    if r.take(6) != MAGIC or r.uint32() != VERSION:
        raise SigError("not an SSHSIG signature of version 1")
    key, namespace, _reserved, hash_name, signature = r.string(), r.string(), r.string(), r.string(), r.string()
    r.end()
    try:
        ns, hn = namespace.decode("utf-8"), hash_name.decode("ascii")
    except UnicodeDecodeError:
        raise SigError("the signature's namespace or hash name is not text") from None
    if hn not in HASHES:
        raise SigError(f"hash {hn!r} is not one SSHSIG allows (sha512, sha256)")
    return SshSig(key, ns, hn, signature)


def verify(sig: SshSig, message: bytes, namespace: str) -> PublicKey:
    """Check ``sig`` over ``message`` in ``namespace`` with the key it carries; that key (SigError: it fails).

    Which keys to trust is the caller's (``signers``): this says only that the key made this signature."""
    if sig.namespace != namespace:
        raise SigError(f"made for namespace {sig.namespace!r}, not {namespace!r}")
    key = public_from_blob(sig.public_key)
    r = _Reader(sig.signature)
    kind, raw = r.string().decode("ascii", "replace"), r.string()
    r.end()
    data = _signed_data(namespace, sig.hash_name, message)
    try:
        _check(key, kind, raw, data)
    except InvalidSignature:
        raise SigError("the signature does not match the content (a changed byte, or another key)") from None
    return key


def _check(key: PublicKey, kind: str, raw: bytes, data: bytes) -> None:
    if isinstance(key, ed25519.Ed25519PublicKey):
        if kind != "ssh-ed25519":
            raise SigError(f"an Ed25519 key with a {kind} signature")
        key.verify(raw, data)
    elif isinstance(key, ec.EllipticCurvePublicKey):
        name = next((n for n, (_, curve, _h) in _CURVES.items() if isinstance(key.curve, curve)), None)
        if name is None or kind != name:
            raise SigError(f"an ECDSA key with a {kind} signature")
        inner = _Reader(raw)
        r, s = inner.mpint(), inner.mpint()
        inner.end()
        key.verify(encode_dss_signature(r, s), data, ec.ECDSA(_CURVES[name][2]))
    else:
        algorithms: dict[str, Any] = {"rsa-sha2-512": hashes.SHA512(), "rsa-sha2-256": hashes.SHA256()}
        if kind not in algorithms:  # ssh-rsa is SHA-1: OpenSSH refuses it for SSHSIG too
            raise SigError(f"RSA signature {kind} is not accepted (rsa-sha2-512 or rsa-sha2-256)")
        key.verify(raw, data, padding.PKCS1v15(), algorithms[kind])
