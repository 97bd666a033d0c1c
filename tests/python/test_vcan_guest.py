"""The qemu guest builder of the virtual-CAN tests (scripts/vcan_guest/): its pieces on synthetic
inputs, and the runner's refusal to skip. The guest itself runs in ctest (vcan_guest)."""
from __future__ import annotations

import gzip
import importlib.util
import lzma
import os
import shutil
import subprocess
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
RUNNER = REPO / "scripts" / "vcan_guest" / "run.sh"


def _load_builder():
    spec = importlib.util.spec_from_file_location("build_guest", REPO / "scripts" / "vcan_guest" / "build_guest.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


bg = _load_builder()


def test_extract_vmlinux_finds_the_compressed_elf_after_false_magics():
    elf = b"\x7fELF" + bytes(range(256)) * 40
    payload = lzma.compress(elf, format=lzma.FORMAT_XZ)
    # a stray xz magic before the real stream, and trailing bytes after it (as in a bzImage)
    image = b"MZ" + bytes(500) + bg.XZ_MAGIC + b"garbage" + bytes(100) + payload + b"\x00trailer" * 10
    assert bg.extract_vmlinux(image) == elf
    gz = b"junk" + gzip.compress(elf, mtime=0)
    assert bg.extract_vmlinux(gz) == elf
    with pytest.raises(bg.GuestError):
        bg.extract_vmlinux(b"no kernel in here" * 100)


def _fake_ko(depends: str) -> bytes:
    return b"\x7fELF...\x00license=GPL\x00depends=" + depends.encode() + b"\x00vermagic=6.1\x00"


def test_modules_come_in_dependency_order_and_decompressed(tmp_path):
    (tmp_path / "net" / "can").mkdir(parents=True)
    (tmp_path / "drivers").mkdir()
    (tmp_path / "net" / "can" / "can.ko.xz").write_bytes(lzma.compress(_fake_ko("")))
    (tmp_path / "net" / "can" / "can-raw.ko").write_bytes(_fake_ko("can"))
    (tmp_path / "drivers" / "can-dev.ko.gz").write_bytes(gzip.compress(_fake_ko("can_skb_helper")))
    (tmp_path / "drivers" / "can_skb_helper.ko").write_bytes(_fake_ko(""))
    (tmp_path / "drivers" / "vcan.ko").write_bytes(_fake_ko("can-dev,can"))
    order = [name for name, _ in bg.resolve_modules(tmp_path)]
    assert sorted(order) == sorted(["can", "can-raw", "can-skb-helper", "can-dev", "vcan"])
    for mod, dep in (("can-raw", "can"), ("can-dev", "can-skb-helper"), ("vcan", "can-dev"), ("vcan", "can")):
        assert order.index(dep) < order.index(mod), order
    blobs = dict(bg.resolve_modules(tmp_path))
    assert blobs["can"].startswith(b"\x7fELF") and blobs["can-dev"].startswith(b"\x7fELF")
    (tmp_path / "drivers" / "can_skb_helper.ko").unlink()
    with pytest.raises(bg.GuestError, match="can_skb_helper|can-skb-helper"):
        bg.resolve_modules(tmp_path)


def test_static_elf_detection():
    assert bg.is_static_elf(Path("/bin/busybox")), "busybox-static is installed by scripts/setup.sh"
    assert not bg.is_static_elf(Path(shutil.which("ls")))


def test_initramfs_is_a_newc_archive_with_init_modules_and_tests(tmp_path):
    cache = tmp_path / "cache"
    (cache / "modules").mkdir(parents=True)
    (cache / "modules" / "can.ko").write_bytes(_fake_ko(""))
    out = tmp_path / "initramfs.cpio.gz"
    bg.build_initramfs(cache, {"modules": ["can"]}, [Path("/bin/busybox")], out)
    raw = gzip.decompress(out.read_bytes())
    assert raw.startswith(b"070701")
    names = []
    i = 0
    while i < len(raw):  # walk the newc headers
        assert raw[i:i + 6] == b"070701"
        fsize, nsize = int(raw[i + 54:i + 62], 16), int(raw[i + 94:i + 102], 16)
        name = raw[i + 110:i + 110 + nsize - 1].decode()
        i += 110 + nsize
        i += (-i) % 4
        data = raw[i:i + fsize]
        i += fsize
        i += (-i) % 4
        if name == "TRAILER!!!":
            break
        names.append(name)
        if name == "init":
            assert b"insmod /lib/modules/$m.ko" in data and b"for m in can;" in data
            assert b"DDYN_GUEST_EXIT" in data and b"type vcan" in data
    assert {"init", "bin/busybox", "lib/modules/can.ko", "tests/busybox"} <= set(names)
    # reproducible: the same inputs give the same bytes
    out2 = tmp_path / "again.cpio.gz"
    bg.build_initramfs(cache, {"modules": ["can"]}, [Path("/bin/busybox")], out2)
    assert out.read_bytes() == out2.read_bytes()
    with pytest.raises(bg.GuestError, match="dynamically linked"):
        bg.build_initramfs(cache, {"modules": ["can"]}, [Path(shutil.which("ls"))], out)


def test_runner_fails_loudly_without_qemu(tmp_path):
    """No qemu on PATH and no host vcan: a failure with a reason, never a skip."""
    bindir = tmp_path / "bin"
    bindir.mkdir()
    for tool in ("bash", "dirname", "mkdir", "rm", "python3", "ip", "cat", "date", "awk", "grep", "tr", "timeout"):
        path = shutil.which(tool)
        if path:
            os.symlink(path, bindir / tool)
    env = dict(os.environ, PATH=str(bindir), DDYN_VCAN_MODE="guest", DDYN_VCAN_GUEST_DIR=str(tmp_path / "cache"))
    r = subprocess.run(["bash", str(RUNNER), "/bin/busybox"], env=env, capture_output=True, text=True)
    assert r.returncode == 1
    assert "FAIL: qemu-system-x86_64 not installed" in r.stdout
