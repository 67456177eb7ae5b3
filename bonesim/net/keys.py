"""Shared packet keys: reading one (a key file, raw or hex, or the
``BONESIM_KEY`` environment variable), writing a new one, and fresh nonces."""
from __future__ import annotations

import math
import os
import secrets
import string
import zlib
from pathlib import Path

from bonesim.errors import BonesimError
from bonesim.io.limits import setting

__all__ = ["MIN_KEY_BYTES", "KEY_ENV", "DEFAULT_KEY_HELP", "key_entropy_bits",
           "min_key_bits", "load_key", "write_key", "new_nonce"]

#: Smallest accepted key [bytes].
MIN_KEY_BYTES = 16
#: Environment variable holding the key (hex) when no key file is given.
KEY_ENV = "BONESIM_KEY"
DEFAULT_KEY_HELP = f"shared key file (default: ${KEY_ENV}, hex)"


#: Alphabets a text key may be drawn from, smallest first, and their bits
#: per character.
_ALPHABETS = tuple((frozenset(chars.encode()), math.log2(len(set(chars)))) for chars in (
    string.digits, string.hexdigits, string.ascii_lowercase, string.ascii_uppercase,
    string.ascii_letters + string.digits,
    "".join(chr(c) for c in range(32, 127))))


def min_key_bits() -> float:
    """The least estimated entropy a key may have [bits] (``[network]
    min_key_entropy_bits`` of ``bonesim/data/limits.toml``)."""
    return float(setting("network", "min_key_entropy_bits"))


def key_entropy_bits(key: bytes) -> float:
    """An upper estimate of a key's entropy [bits].

    The least of: 8 bits a byte; the key's shortest repeating unit times the
    bits per character of the smallest alphabet holding it (digits, hex,
    lower or upper case letters, letters and digits, printable ASCII, any
    byte); and 8 bits per byte of its raw-deflate compression (repeats and
    runs compress). ``passwordpassword`` gets 38 bits, 16 zero bytes 8, 16
    random bytes 128, a ``bonesim tutor keygen`` key 256.

    Parameters
    ----------
    key : bytes

    Returns
    -------
    float
        [bits]
    """
    n = len(key)
    if n == 0:
        return 0.0
    period = next(p for p in range(1, n + 1)
                  if all(key[i] == key[i % p] for i in range(n)))
    chars = set(key)
    per_char = next((bits for alphabet, bits in _ALPHABETS if chars <= alphabet), 8.0)
    z = zlib.compressobj(9, zlib.DEFLATED, -15)
    deflated = len(z.compress(key) + z.flush())
    return float(min(8 * n, period * per_char, 8 * (deflated + 2)))   # 2: block overhead


def _parse_key(raw: bytes) -> bytes:
    text = raw.strip()
    if text and len(text) % 2 == 0:
        try:
            return bytes.fromhex(text.decode("ascii"))
        except (UnicodeDecodeError, ValueError):
            pass
    return raw


def load_key(path: str | Path | None = None) -> bytes:
    """The shared packet key.

    Parameters
    ----------
    path : str or Path, optional
        Key file: hex text (as :func:`write_key` writes) or raw bytes. Without
        it the key is taken from the environment variable ``BONESIM_KEY``
        (hex, or else the text itself).

    Returns
    -------
    bytes
        At least :data:`MIN_KEY_BYTES` bytes.

    Raises
    ------
    BonesimError
        No key, an unreadable file, a key shorter than 16 bytes, or one
        with less than :func:`min_key_bits` of estimated entropy
        (:func:`key_entropy_bits`).
    """
    if path is None:
        env = os.environ.get(KEY_ENV)
        if not env:
            raise BonesimError(f"no key: pass a key file (--key-file) or set {KEY_ENV}; "
                               "'bonesim tutor keygen FILE' makes one", field=KEY_ENV)
        key = _parse_key(env.encode())
        where = {"field": KEY_ENV}
    else:
        p = Path(path)
        try:
            raw = p.read_bytes()
        except FileNotFoundError:
            raise BonesimError("key file not found ('bonesim tutor keygen FILE' makes "
                               "one)", path=p) from None
        except OSError as exc:
            raise BonesimError(f"cannot read key file: {exc.strerror}", path=p) from None
        key = _parse_key(raw)
        where = {"path": p}
    if len(key) < MIN_KEY_BYTES:
        raise BonesimError(f"key is {len(key)} bytes; at least {MIN_KEY_BYTES} are needed "
                           "(32 random bytes recommended)", **where)
    bits, need = key_entropy_bits(key), min_key_bits()
    if bits < need:
        raise BonesimError(f"key is too weak: about {bits:.0f} bits of entropy (a word, a "
                           f"repeated pattern or few distinct bytes), at least {need:.0f} "
                           "are needed; 'bonesim tutor keygen FILE' makes a random one",
                           **where)
    return key


def write_key(path: str | Path, n_bytes: int = 32, overwrite: bool = False) -> Path:
    """Write a new random key as hex text, readable by the owner only.

    Raises
    ------
    BonesimError
        If the file exists (and ``overwrite`` is False) or cannot be written.
    """
    p = Path(path)
    if n_bytes < MIN_KEY_BYTES:
        raise ValueError(f"keys need at least {MIN_KEY_BYTES} bytes")
    flags = os.O_WRONLY | os.O_CREAT | (os.O_TRUNC if overwrite else os.O_EXCL)
    try:
        fd = os.open(p, flags, 0o600)
    except FileExistsError:
        raise BonesimError("key file exists; refusing to overwrite it", path=p) from None
    except OSError as exc:
        raise BonesimError(f"cannot write key file: {exc.strerror}", path=p) from None
    with os.fdopen(fd, "w") as fh:
        fh.write(secrets.token_hex(n_bytes) + "\n")
    return p


def new_nonce() -> int:
    """A fresh random non-zero session nonce (u64)."""
    while True:
        n = secrets.randbits(64)
        if n:
            return n
