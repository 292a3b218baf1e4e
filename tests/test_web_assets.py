"""The web view's pinned browser libraries: a tarball whose hash differs is refused, nothing unpacked."""

from __future__ import annotations

import io
import tarfile
from pathlib import Path

import pytest
from ogserver.web import assets


def tarball(files: dict[str, bytes]) -> bytes:
    buffer = io.BytesIO()
    with tarfile.open(fileobj=buffer, mode="w:gz") as archive:
        for name, data in files.items():
            info = tarfile.TarInfo(f"package/{name}")
            info.size = len(data)
            archive.addfile(info, io.BytesIO(data))
    return buffer.getvalue()


def test_pins_name_a_licence_and_sha512() -> None:
    for package in assets.PACKAGES:
        assert package.integrity.startswith("sha512-") and package.files[0] == "LICENSE"


def test_a_tarball_with_another_hash_is_refused(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(assets, "VENDOR", tmp_path / "vendor")
    source = tmp_path / "lib.tgz"
    source.write_bytes(tarball({"LICENSE": b"MIT", "lib.js": b"export {}"}))
    package = assets.Package("lib", "1.0.0", "sha512-" + "A" * 86 + "==", ("LICENSE", "lib.js"))
    with pytest.raises(ValueError, match="integrity check failed"):
        assets.install(package, source)
    assert not package.folder.exists()


def test_a_verified_tarball_is_unpacked(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    import base64
    import hashlib

    monkeypatch.setattr(assets, "VENDOR", tmp_path / "vendor")
    data = tarball({"LICENSE": b"MIT", "dist/lib.js": b"export {}", "other.js": b""})
    source = tmp_path / "lib.tgz"
    source.write_bytes(data)
    integrity = "sha512-" + base64.b64encode(hashlib.sha512(data).digest()).decode()
    package = assets.Package("@scope/lib", "1.0.0", integrity, ("LICENSE", "dist/lib.js"))
    assets.install(package, source)
    assert assets.installed(package)
    assert sorted(path.name for path in package.folder.rglob("*") if path.is_file()) == [".version", "LICENSE",
                                                                                          "lib.js"]
