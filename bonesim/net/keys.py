"""Shared packet keys: reading one (a key file, raw or hex, or the
``BONESIM_KEY`` environment variable), writing a new one, and fresh nonces."""
from __future__ import annotations

import os
import secrets
from pathlib import Path

from bonesim.errors import BonesimError

__all__ = ["MIN_KEY_BYTES", "KEY_ENV", "DEFAULT_KEY_HELP", "load_key", "write_key",
           "new_nonce"]

#: Smallest accepted key [bytes].
MIN_KEY_BYTES = 16
#: Environment variable holding the key (hex) when no key file is given.
KEY_ENV = "BONESIM_KEY"
DEFAULT_KEY_HELP = f"shared key file (default: ${KEY_ENV}, hex)"


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
        No key, an unreadable file, or a key shorter than 16 bytes.
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
