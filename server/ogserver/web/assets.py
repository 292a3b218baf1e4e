"""The browser libraries the web view serves, pinned by version and the npm registry's sha512.

``python -m ogserver.web.assets`` (the Makefile's venv step) downloads each package's tarball once,
checks its integrity and unpacks the few files the page loads, with the package's licence, into
``vendor/`` beside this module (git-ignored). The server serves them itself: no network at run
time, and no Node or npm anywhere. Spark bundles its own dependencies (fflate, its WebAssembly and
its worker); it imports three and one three.js add-on, which the page maps with an import map.
"""

from __future__ import annotations

import argparse
import base64
import hashlib
import io
import shutil
import sys
import tarfile
import urllib.request
from dataclasses import dataclass
from pathlib import Path

VENDOR = Path(__file__).parent / "vendor"
REGISTRY = "https://registry.npmjs.org"
DOWNLOAD_SECONDS = 120.0


@dataclass(frozen=True)
class Package:
    name: str
    version: str
    integrity: str  # "sha512-<base64>", as the registry's dist.integrity
    files: tuple[str, ...]  # paths inside the tarball's package/ folder, the licence first

    @property
    def folder(self) -> Path:
        return VENDOR / self.name.rsplit("/", 1)[-1]

    @property
    def tarball(self) -> str:
        return f"{REGISTRY}/{self.name}/-/{self.name.rsplit('/', 1)[-1]}-{self.version}.tgz"


# Spark 2.2.0 asks for three >= 0.180.0 (its peer dependency) and was built against 0.180.
PACKAGES = (
    Package("three", "0.180.0",
            "sha512-o+qycAMZrh+TsE01GqWUxUIKR1AL0S8pq7zDkYOQw8GqfX8b8VoCKYUoHbhiX5j+7hr8XsuHDVU6+gkQJQKg9w==",
            ("LICENSE", "build/three.module.js", "build/three.core.js", "examples/jsm/postprocessing/Pass.js")),
    Package("@sparkjsdev/spark", "2.2.0",
            "sha512-wf5F2YAmPXnjm20/MgXYer9FQTXz2JOCo05HwxFkaD7Guk9rHVPIwdJ6fq0oF9ME0heMvYj+TxS6DTrucvy6KA==",
            ("LICENSE", "dist/spark.module.js")),
)


def installed(package: Package) -> bool:
    stamp = package.folder / ".version"
    return stamp.is_file() and stamp.read_text().strip() == f"{package.version} {package.integrity}" and all(
        (package.folder / name).is_file() for name in package.files)


def missing() -> list[Package]:
    return [package for package in PACKAGES if not installed(package)]


def verify(data: bytes, integrity: str) -> None:
    algorithm, _, expected = integrity.partition("-")
    if algorithm != "sha512" or base64.b64encode(hashlib.sha512(data).digest()).decode() != expected:
        raise ValueError(f"integrity check failed: the tarball's sha512 is not {integrity}")


def install(package: Package, source: Path | None = None) -> None:
    """Fetch (or read ``source``), verify and unpack ``package``'s files into its vendor folder."""
    if source is not None:
        data = source.read_bytes()
    else:
        with urllib.request.urlopen(package.tarball, timeout=DOWNLOAD_SECONDS) as response:
            data = response.read()
    verify(data, package.integrity)
    shutil.rmtree(package.folder, ignore_errors=True)
    with tarfile.open(fileobj=io.BytesIO(data), mode="r:gz") as archive:
        for name in package.files:
            member = archive.extractfile(f"package/{name}")
            if member is None:
                raise ValueError(f"{package.name} {package.version}: no file {name} in its tarball")
            target = package.folder / name
            target.parent.mkdir(parents=True, exist_ok=True)
            target.write_bytes(member.read())
    (package.folder / ".version").write_text(f"{package.version} {package.integrity}\n")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m ogserver.web.assets", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--check", action="store_true", help="only say whether they are installed (exit 1 if not)")
    args = parser.parse_args(argv)
    todo = missing()
    if args.check:
        print("web assets: " + (", ".join(f"{p.name} {p.version} missing" for p in todo) or "installed"))
        return 1 if todo else 0
    for package in todo:
        try:
            install(package)
        except (OSError, ValueError) as error:
            print(f"web assets: {package.name} {package.version}: {error}", file=sys.stderr)
            return 1
        print(f"web assets: {package.name} {package.version} verified, in {package.folder}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
