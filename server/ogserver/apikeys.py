"""API keys: the server keeps only each key's sha256, under the name that owns its sessions.

``python -m ogserver.apikeys NAME`` makes a new key: it prints the key (give it to the client,
once) and the line for the server's ``api_keys_file``.
"""

from __future__ import annotations

import hashlib
import re
import secrets
import sys
from pathlib import Path

from ogserver.settings import SHA256_HEX, Access

NAME = re.compile(r"[A-Za-z0-9_.@-]{1,64}")


def digest(key: str) -> str:
    return hashlib.sha256(key.encode()).hexdigest()


def parse(text: str, source: str) -> dict[str, str]:
    """``NAME:SHA256HEX`` lines (``#`` comments and blank lines allowed) as NAME -> digest."""
    keys: dict[str, str] = {}
    for number, line in enumerate(text.splitlines(), 1):
        line = line.split("#", 1)[0].strip()
        if not line:
            continue
        name, _, hexdigest = (part.strip() for part in line.partition(":"))
        if not NAME.fullmatch(name) or not SHA256_HEX.fullmatch(hexdigest) or name in keys:
            raise ValueError(f"{source}:{number}: expected a new NAME:SHA256HEX (64 lowercase hex digits)")
        keys[name] = hexdigest
    return keys


def load(access: Access) -> dict[str, str]:
    """Every accepted key's digest -> its name, from the settings and the keys file."""
    names = dict(access.api_keys)
    if access.api_keys_file:
        path = Path(access.api_keys_file)
        try:
            text = path.read_text()
        except OSError as error:
            raise ValueError(f"access.api_keys_file: cannot read {path}: {error.strerror}") from None
        names.update(parse(text, str(path)))
    for name in names:
        if not NAME.fullmatch(name):
            raise ValueError(f"API key name {name!r}: use 1-64 letters, digits or _.@-")
    return {hexdigest: name for name, hexdigest in names.items()}


def main(argv: list[str] | None = None) -> int:
    args = sys.argv[1:] if argv is None else argv
    if len(args) != 1 or not NAME.fullmatch(args[0]):
        print("usage: python -m ogserver.apikeys NAME   (NAME: 1-64 letters, digits or _.@-)", file=sys.stderr)
        return 2
    key = secrets.token_urlsafe(32)
    print(f"key (give it to the client; the server keeps only its hash): {key}")
    print(f"line for the server's api_keys_file: {args[0]}:{digest(key)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
