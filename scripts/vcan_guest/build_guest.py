#!/usr/bin/env python3
"""Build the small Linux guest in which the virtual-CAN tests run (these hosts' kernels have no CAN).

  kernel   Debian's linux-image-amd64 (not the cloud flavour, which has no CAN): the versioned
           linux-image-<ver>-amd64 package it depends on is fetched with `apt-get download`,
           unpacked with `dpkg-deb -x`, and its bzImage's xz payload decompressed to an ELF
           vmlinux (what the kernel source's scripts/extract-vmlinux does), which qemu boots
           directly through its PVH entry point, skipping the guest-side decompression.
  modules  can, can-raw, can-dev, vcan and whatever they depend on (the `depends=` field of each
           module's .modinfo), in dependency order, decompressed (.ko.xz/.ko.zst/.ko.gz) here so
           the guest's busybox insmod needs no decompressor.
  initramfs busybox-static, the modules, the test binaries (statically linked: the guest has no
           libc) and an /init that loads the modules, creates vcan0 (MTU 72: CAN FD capable), runs the tests and prints
           "DDYN_GUEST_EXIT: <status>" on the serial console.
  dynamic  for other guests (`ddyn sil run`'s, whose controller and lcm-logger link liblcm and GLib):
           add_binaries() copies a dynamically linked executable with its ELF interpreter (at its
           PT_INTERP path) and the shared-library closure ldd resolves on this host, into
           GUEST_LIB_DIR (the guest's /init exports LD_LIBRARY_PATH=GUEST_LIB_DIR). A library ldd
           cannot find is an error naming it.

The kernel and modules are cached in the cache directory (default build/vcan-guest, outside
git) and fetched only once; the initramfs is rebuilt on each call (it holds the test binaries).
Any missing piece is an error, never a silent skip.

usage: build_guest.py [--cache DIR] --initramfs OUT.cpio.gz TEST_BINARY [TEST_BINARY ...]
"""
from __future__ import annotations

import argparse
import gzip
import io
import json
import lzma
import os
import re
import shutil
import stat
import struct
import subprocess
import sys
import zlib
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
DEFAULT_CACHE = ROOT / "build" / "vcan-guest"
WANTED_MODULES = ("can", "can-raw", "can-dev", "vcan")
BUSYBOX = Path("/bin/busybox")
GUEST_LIB_DIR = "/lib/ddyn"  # shared libraries of dynamically linked guest binaries (LD_LIBRARY_PATH)
XZ_MAGIC = b"\xfd7zXZ\x00"
GZIP_MAGIC = b"\x1f\x8b\x08"


class GuestError(RuntimeError):
    pass


def log(msg: str) -> None:
    print(f"vcan-guest: {msg}", file=sys.stderr, flush=True)


def run(cmd: list[str], cwd: Path | None = None) -> str:
    r = subprocess.run(cmd, cwd=cwd, capture_output=True, text=True)
    if r.returncode != 0:
        raise GuestError(f"`{' '.join(cmd)}` failed ({r.returncode}): {r.stderr.strip()[-800:]}")
    return r.stdout


def kernel_package() -> str:
    """The versioned image package linux-image-amd64 depends on (apt-cache depends)."""
    out = run(["apt-cache", "depends", "linux-image-amd64"])
    names = re.findall(r"Depends:\s*(linux-image-[0-9][^\s]*-amd64)\b", out)
    names = [n for n in names if "cloud" not in n]
    if not names:
        raise GuestError(f"apt-cache depends linux-image-amd64 names no versioned kernel image:\n{out}")
    return names[0]


def fetch_kernel_deb(pkg: str, debdir: Path) -> Path:
    debdir.mkdir(parents=True, exist_ok=True)
    debs = sorted(debdir.glob(f"{pkg}_*.deb"))
    if debs:
        return debs[-1]
    log(f"apt-get download {pkg}")
    try:
        run(["apt-get", "download", pkg], cwd=debdir)
    except GuestError:
        log("apt-get download failed; refreshing the package lists once and retrying")
        sudo = [] if os.geteuid() == 0 else ["sudo"]
        run(sudo + ["apt-get", "update", "-qq"])
        run(["apt-get", "download", pkg], cwd=debdir)
    debs = sorted(debdir.glob(f"{pkg}_*.deb"))
    if not debs:
        raise GuestError(f"apt-get download {pkg} left no .deb in {debdir}")
    return debs[-1]


def extract_vmlinux(bzimage: bytes) -> bytes:
    """The ELF kernel inside a bzImage: decompress the payload from its first valid xz/gzip stream."""
    for magic, decompress in ((XZ_MAGIC, _unxz), (GZIP_MAGIC, _gunzip)):
        start = 0
        for _ in range(64):  # a few false positives of the magic before the real payload, at most
            i = bzimage.find(magic, start)
            if i < 0:
                break
            try:
                elf = decompress(bzimage[i:])
            except (lzma.LZMAError, OSError, EOFError, zlib.error):
                elf = b""
            if elf[:4] == b"\x7fELF":
                return elf
            start = i + 1
    raise GuestError("no xz or gzip compressed ELF kernel found inside the bzImage")


def _unxz(data: bytes) -> bytes:
    d = lzma.LZMADecompressor(format=lzma.FORMAT_XZ)
    return d.decompress(data)  # trailing data after the stream is left in d.unused_data


def _gunzip(data: bytes) -> bytes:
    d = zlib.decompressobj(16 + zlib.MAX_WBITS)
    return d.decompress(data)


def module_bytes(path: Path) -> bytes:
    data = path.read_bytes()
    if path.name.endswith(".ko.xz"):
        return lzma.decompress(data)
    if path.name.endswith(".ko.gz"):
        return gzip.decompress(data)
    if path.name.endswith(".ko.zst"):
        if shutil.which("zstd") is None:
            raise GuestError(f"{path} is zstd-compressed and zstd is not installed (scripts/setup.sh installs it)")
        return subprocess.run(["zstd", "-dc", str(path)], capture_output=True, check=True).stdout
    return data


def module_name(path: Path) -> str:
    return re.sub(r"\.ko(\.(xz|gz|zst))?$", "", path.name)


def module_depends(ko: bytes) -> list[str]:
    m = re.search(rb"(?:^|\x00)depends=([^\x00]*)\x00", ko)
    if not m or not m.group(1):
        return []
    return [d.decode() for d in m.group(1).split(b",") if d]


def resolve_modules(moddir: Path) -> list[tuple[str, bytes]]:
    index: dict[str, Path] = {}
    for p in moddir.rglob("*.ko*"):
        index.setdefault(module_name(p).replace("_", "-"), p)
    order: list[tuple[str, bytes]] = []
    done: set[str] = set()

    # iterative depth-first walk (no recursion), each module once, dependencies first
    for top in WANTED_MODULES:
        stack: list[tuple[str, bool]] = [(top, False)]
        guard = 0
        while stack:
            guard += 1
            if guard > 10000:
                raise GuestError("module dependency walk did not terminate")
            name, expanded = stack.pop()
            key = name.replace("_", "-")
            if key in done:
                continue
            if key not in index:
                raise GuestError(f"kernel module {name} not found under {moddir}")
            ko = module_bytes(index[key])
            if expanded:
                done.add(key)
                order.append((key, ko))
                continue
            stack.append((name, True))
            for dep in module_depends(ko):
                if dep.replace("_", "-") not in done:
                    stack.append((dep, False))
    return order


def prepare_kernel(cache: Path) -> dict:
    stamp = cache / "kernel.json"
    if stamp.is_file():
        meta = json.loads(stamp.read_text())
        if (cache / meta["vmlinux"]).is_file() and all((cache / "modules" / f"{m}.ko").is_file()
                                                       for m in meta["modules"]):
            return meta
    pkg = kernel_package()
    deb = fetch_kernel_deb(pkg, cache / "deb")
    root = cache / "root"
    if root.exists():
        shutil.rmtree(root)
    log(f"dpkg-deb -x {deb.name}")
    run(["dpkg-deb", "-x", str(deb), str(root)])
    vmlinuz = sorted((root / "boot").glob("vmlinuz-*"))
    if not vmlinuz:
        raise GuestError(f"{deb.name} holds no /boot/vmlinuz-*")
    release = vmlinuz[0].name[len("vmlinuz-"):]
    (cache / "vmlinux").write_bytes(extract_vmlinux(vmlinuz[0].read_bytes()))
    moddir = root / "lib" / "modules" / release
    mods = resolve_modules(moddir)
    out = cache / "modules"
    if out.exists():
        shutil.rmtree(out)
    out.mkdir(parents=True)
    for name, ko in mods:
        (out / f"{name}.ko").write_bytes(ko)
    meta = {"package": pkg, "deb": deb.name, "release": release, "vmlinux": "vmlinux",
            "modules": [name for name, _ in mods]}
    stamp.write_text(json.dumps(meta, indent=1) + "\n")
    shutil.rmtree(root)  # the modules and the kernel are all the guest needs
    log(f"kernel {release} ready in {cache} (modules in order: {', '.join(meta['modules'])})")
    return meta


def is_static_elf(path: Path) -> bool:
    """An ELF executable without a PT_INTERP program header needs no dynamic loader."""
    data = path.read_bytes()
    if data[:4] != b"\x7fELF" or data[4] != 2:
        return False
    endian = "<" if data[5] == 1 else ">"
    phoff = struct.unpack_from(endian + "Q", data, 0x20)[0]
    phentsize, phnum = struct.unpack_from(endian + "HH", data, 0x36)
    for i in range(phnum):
        if struct.unpack_from(endian + "I", data, phoff + i * phentsize)[0] == 3:  # PT_INTERP
            return False
    return True


def elf_interpreter(path: Path) -> str | None:
    """The PT_INTERP path of an ELF executable (None: static)."""
    data = path.read_bytes()
    if data[:4] != b"\x7fELF" or data[4] != 2:
        raise GuestError(f"{path} is not a 64-bit ELF file")
    endian = "<" if data[5] == 1 else ">"
    phoff = struct.unpack_from(endian + "Q", data, 0x20)[0]
    phentsize, phnum = struct.unpack_from(endian + "HH", data, 0x36)
    for i in range(phnum):
        off = phoff + i * phentsize
        if struct.unpack_from(endian + "I", data, off)[0] == 3:  # PT_INTERP
            p_offset, _, _, p_filesz = struct.unpack_from(endian + "QQQQ", data, off + 8)
            return data[p_offset:p_offset + p_filesz].split(b"\x00")[0].decode()
    return None


def parse_ldd(binary: Path, text: str) -> dict[str, Path]:
    """soname -> resolved path from ldd's output; a library ldd cannot find is an error naming it."""
    libs: dict[str, Path] = {}
    missing = []
    for line in text.splitlines():
        line = line.strip()
        m = re.match(r"(\S+) => (.+?)(?: \(0x[0-9a-f]+\))?$", line)
        if m:
            if m.group(2).strip() == "not found":
                missing.append(m.group(1))
            else:
                libs[m.group(1)] = Path(m.group(2).strip())
    if missing:
        raise GuestError(f"{binary} needs {', '.join(missing)}, which ldd cannot find on this host; "
                         "the guest would not start it (install the library, or fix its RUNPATH)")
    return libs


def shared_closure(binary: Path) -> tuple[str, dict[str, Path]]:
    """The ELF interpreter and every shared library (soname -> host path) a dynamic executable loads."""
    interp = elf_interpreter(binary)
    if interp is None:
        raise GuestError(f"{binary} is statically linked: it has no shared-library closure")
    if shutil.which("ldd") is None:
        raise GuestError("ldd is not installed: cannot resolve the shared libraries of dynamic guest binaries")
    r = subprocess.run(["ldd", str(binary)], capture_output=True, text=True)
    if r.returncode != 0:
        raise GuestError(f"ldd {binary} failed ({r.returncode}): {(r.stdout + r.stderr).strip()[-400:]}")
    libs = parse_ldd(binary, r.stdout)
    libs.pop(Path(interp).name, None)
    for name, path in libs.items():
        if not path.is_file():
            raise GuestError(f"{binary}: ldd resolved {name} to {path}, which is not a file")
    if not Path(interp).is_file():
        raise GuestError(f"{binary}: its ELF interpreter {interp} does not exist on this host")
    return interp, libs


def add_binaries(cpio: "Cpio", dest: str, binaries: list[Path]) -> dict:
    """Put executables into the archive under dest/ (which must exist in it); for dynamically linked
    ones also their interpreter and shared libraries (once each; directories created as needed).
    Returns what was added: {"dynamic": [names], "interpreters": [...], "libraries": {soname: host path},
    "bytes": total size of the libraries and interpreters}."""
    interps: set[str] = set()
    libs: dict[str, Path] = {}
    dynamic = []
    for b in binaries:
        if not b.is_file():
            raise GuestError(f"guest binary {b} does not exist")
        if not is_static_elf(b):
            interp, closure = shared_closure(b)
            interps.add(interp)
            for name, path in closure.items():
                if name in libs and libs[name].resolve() != path.resolve():
                    raise GuestError(f"{name}: two different libraries ({libs[name]}, {path}) for one guest")
                libs[name] = path
            dynamic.append(b.name)
        cpio.file(f"{dest}/{b.name}", b.read_bytes())
    size = 0
    if libs or interps:
        made = set(cpio.dirs)
        for d in [GUEST_LIB_DIR.strip("/")] + [str(Path(i).parent).strip("/") for i in sorted(interps)]:
            parts = d.split("/")
            for k in range(1, len(parts) + 1):
                sub = "/".join(parts[:k])
                if sub and sub not in made:
                    cpio.dir(sub)
                    made.add(sub)
        for i in sorted(interps):
            data = Path(i).read_bytes()
            size += len(data)
            cpio.file(i.strip("/"), data)
        for name in sorted(libs):
            data = libs[name].read_bytes()
            size += len(data)
            cpio.file(f"{GUEST_LIB_DIR.strip('/')}/{name}", data)
    return {"dynamic": dynamic, "interpreters": sorted(interps),
            "libraries": {k: str(v) for k, v in sorted(libs.items())}, "bytes": size}


INIT = """#!/bin/busybox sh
/bin/busybox --install -s /bin
mount -t proc proc /proc
mount -t sysfs sysfs /sys
mount -t devtmpfs devtmpfs /dev 2>/dev/null
status=0
for m in {modules}; do
  insmod /lib/modules/$m.ko || {{ echo "DDYN_GUEST: insmod $m failed"; status=1; }}
done
if [ $status -eq 0 ]; then
  # MTU 72 (CANFD_MTU): vcan then carries CAN FD frames as well as classic ones
  ip link add dev vcan0 type vcan && ip link set vcan0 mtu 72 && ip link set up vcan0 || {{ echo "DDYN_GUEST: cannot create vcan0"; status=1; }}
fi
if [ $status -eq 0 ]; then
  for t in {tests}; do
    echo "DDYN_GUEST: up $(cut -d' ' -f1 /proc/uptime) s, running $t"
    /tests/$t vcan0 || status=1
  done
fi
echo "DDYN_GUEST_EXIT: $status"
poweroff -f
"""


class Cpio:
    """A newc cpio archive written in memory (what the kernel unpacks as an initramfs)."""

    def __init__(self) -> None:
        self.buf = io.BytesIO()
        self.ino = 1
        self.dirs: list[str] = []

    def _entry(self, name: str, mode: int, data: bytes = b"", nlink: int = 1) -> None:
        nameb = name.encode() + b"\x00"
        hdr = "070701" + "".join(f"{v:08X}" for v in (
            self.ino, mode, 0, 0, nlink, 0, len(data), 0, 0, 0, 0, len(nameb), 0))
        self.ino += 1
        self.buf.write(hdr.encode() + nameb)
        self.buf.write(b"\x00" * ((4 - (110 + len(nameb)) % 4) % 4))
        self.buf.write(data)
        self.buf.write(b"\x00" * ((4 - len(data) % 4) % 4))

    def dir(self, name: str) -> None:
        self.dirs.append(name)
        self._entry(name, stat.S_IFDIR | 0o755, nlink=2)

    def file(self, name: str, data: bytes, mode: int = 0o755) -> None:
        self._entry(name, stat.S_IFREG | mode, data)

    def finish(self) -> bytes:
        self._entry("TRAILER!!!", 0)
        return self.buf.getvalue()


def build_initramfs(cache: Path, meta: dict, tests: list[Path], out: Path) -> None:
    if not BUSYBOX.is_file() or not is_static_elf(BUSYBOX):
        raise GuestError(f"{BUSYBOX} is missing or not statically linked: install busybox-static (scripts/setup.sh)")
    for t in tests:
        if not t.is_file():
            raise GuestError(f"test binary {t} does not exist")
        if not is_static_elf(t):
            raise GuestError(f"test binary {t} is dynamically linked; the guest has no libc (link with -static)")
    c = Cpio()
    for d in ("bin", "proc", "sys", "dev", "tests", "lib", "lib/modules"):
        c.dir(d)
    c.file("bin/busybox", BUSYBOX.read_bytes())
    for m in meta["modules"]:
        c.file(f"lib/modules/{m}.ko", (cache / "modules" / f"{m}.ko").read_bytes(), 0o644)
    for t in tests:
        c.file(f"tests/{t.name}", t.read_bytes())
    c.file("init", INIT.format(modules=" ".join(meta["modules"]), tests=" ".join(t.name for t in tests)).encode())
    out.parent.mkdir(parents=True, exist_ok=True)
    # mtime 0 and no file name in the gzip header: the same inputs give the same bytes
    with open(out, "wb") as f, gzip.GzipFile(filename="", fileobj=f, mode="wb", compresslevel=1, mtime=0) as gz:
        gz.write(c.finish())


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cache", default=str(DEFAULT_CACHE))
    ap.add_argument("--initramfs", required=True)
    ap.add_argument("tests", nargs="+")
    a = ap.parse_args(argv)
    cache = Path(a.cache)
    cache.mkdir(parents=True, exist_ok=True)
    try:
        meta = prepare_kernel(cache)
        build_initramfs(cache, meta, [Path(t) for t in a.tests], Path(a.initramfs))
    except (GuestError, OSError, subprocess.CalledProcessError) as e:
        print(f"vcan-guest: error: {e}", file=sys.stderr)
        return 1
    print(cache / meta["vmlinux"])
    return 0


if __name__ == "__main__":
    sys.exit(main())
