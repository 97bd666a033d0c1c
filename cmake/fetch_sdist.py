#!/usr/bin/env python3
"""Fetch one pinned source distribution from the package index, verified by SHA-256 before anything uses it.

usage: fetch_sdist.py NAME VERSION SHA256 DIR

The file NAME-VERSION.tar.gz is looked up on the index's simple page (PEP 503; the index is
DDYN_INDEX_URL, else PIP_INDEX_URL, else https://pypi.org/simple), downloaded into a temporary file
in DIR, and its SHA-256 compared with the pinned one (and with the index's own #sha256= fragment
when it gives one) BEFORE it is moved to DIR/NAME-VERSION.tar.gz. Nothing of the archive is
executed: no pip, no build backend, no setup.py (a `pip download --no-binary` would run the
sdist's build backend to read its metadata before any hash check). Idempotent: an archive already
in DIR with the pinned hash is kept. Standard library only. Exit 0 on success, 1 with one line on
stderr otherwise. Used by scripts/fetch_daqp.sh and cmake/third_party.cmake.
"""
from __future__ import annotations

import hashlib
import html.parser
import os
import sys
import tempfile
import urllib.parse
import urllib.request

MAX_BYTES = 64 * 1024 * 1024  # no sdist we pin is near this; a runaway response stops here
TIMEOUT_S = 120


class _Links(html.parser.HTMLParser):
    def __init__(self) -> None:
        super().__init__()
        self.hrefs: list[str] = []

    def handle_starttag(self, tag, attrs):
        if tag == "a":
            for k, v in attrs:
                if k == "href" and v:
                    self.hrefs.append(v)


def sha256_of(path: str) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 16), b""):
            h.update(block)
    return h.hexdigest()


def main(argv: list[str]) -> int:
    if len(argv) != 5:
        print("usage: fetch_sdist.py NAME VERSION SHA256 DIR", file=sys.stderr)
        return 1
    name, version, sha, dest_dir = argv[1], argv[2], argv[3].lower(), argv[4]
    filename = f"{name}-{version}.tar.gz"
    dest = os.path.join(dest_dir, filename)
    os.makedirs(dest_dir, exist_ok=True)
    if os.path.isfile(dest) and sha256_of(dest) == sha:
        return 0
    index = (os.environ.get("DDYN_INDEX_URL") or os.environ.get("PIP_INDEX_URL") or "https://pypi.org/simple").rstrip("/")
    page_url = f"{index}/{name}/"
    if page_url.startswith("file://") and os.path.isdir(urllib.request.url2pathname(page_url[len("file://"):])):
        page_url += "index.html"  # a local index (pip's file:// convention)
    try:
        with urllib.request.urlopen(page_url, timeout=TIMEOUT_S) as r:
            page = r.read(8 * 1024 * 1024).decode("utf-8", "replace")
            page_url = r.geturl()
    except OSError as e:
        print(f"fetch_sdist.py: cannot read the index page {page_url}: {e}", file=sys.stderr)
        return 1
    parser = _Links()
    parser.feed(page)
    matches = [h for h in parser.hrefs
               if urllib.parse.unquote(urllib.parse.urlsplit(h).path.rsplit("/", 1)[-1]) == filename]
    if not matches:
        print(f"fetch_sdist.py: {filename} is not on {page_url}", file=sys.stderr)
        return 1
    href = matches[0]
    url, _, fragment = urllib.parse.urljoin(page_url, href).partition("#")
    if fragment.startswith("sha256=") and fragment[len("sha256="):].lower() != sha:
        print(f"fetch_sdist.py: the index lists {filename} with {fragment}, not the pinned sha256={sha}", file=sys.stderr)
        return 1
    fd, tmp = tempfile.mkstemp(prefix=f".{filename}.", dir=dest_dir)
    try:
        h = hashlib.sha256()
        n = 0
        with os.fdopen(fd, "wb") as out, urllib.request.urlopen(url, timeout=TIMEOUT_S) as r:
            while True:
                block = r.read(1 << 16)
                if not block:
                    break
                n += len(block)
                if n > MAX_BYTES:
                    print(f"fetch_sdist.py: {url} is larger than {MAX_BYTES} bytes", file=sys.stderr)
                    return 1
                h.update(block)
                out.write(block)
        if h.hexdigest() != sha:
            print(f"fetch_sdist.py: {filename} from {url} has SHA-256 {h.hexdigest()}, not the pinned {sha}",
                  file=sys.stderr)
            return 1
        os.chmod(tmp, 0o644)
        os.replace(tmp, dest)
        tmp = ""
    except OSError as e:
        print(f"fetch_sdist.py: cannot download {url}: {e}", file=sys.stderr)
        return 1
    finally:
        if tmp and os.path.exists(tmp):
            os.unlink(tmp)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv))
