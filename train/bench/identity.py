"""Which network a C tool was built for, and the refusal to time another checkpoint's.

The guard network's shapes and weights are compiled into the tools (DDYN_NET_EXPORT_DIR), so a tool
built for one checkpoint silently runs that network whatever checkpoint a command names: the tests'
fixture network, say, after the test command rebuilt the tools. Every tool that links the network
answers `--checkpoint-hash` with the sha256 of the checkpoint its tables were exported from.
"""
from __future__ import annotations

import subprocess
from pathlib import Path

from ddyn.errors import DdynError
from ddyn.learn import checkpoint


def tool_checkpoint_hash(tool: str | Path) -> str:
    """The sha256 of the checkpoint whose exported network `tool` was built with."""
    tool = Path(tool)
    if not tool.is_file():
        raise DdynError(f"{tool} not found: build with scripts/build.sh <dir> -DDDYN_NET_EXPORT_DIR=<export dir>")
    proc = subprocess.run([str(tool), "--checkpoint-hash"], capture_output=True, text=True)
    sha = proc.stdout.strip()
    if proc.returncode != 0 or len(sha) != 64:
        raise DdynError(f"{tool} does not say which network it was built for (rebuild it): {proc.stderr.strip()}")
    return sha


def require_same_network(tool: str | Path, ckpt_path: str | Path) -> str:
    """Refuse, with the fix in the message, a tool built for another checkpoint than `ckpt_path`."""
    built = tool_checkpoint_hash(tool)
    given = checkpoint.file_sha256(Path(ckpt_path))
    if built != given:
        raise DdynError(
            f"{tool} was built for checkpoint {built[:12]}..., not for {ckpt_path} ({given[:12]}...): "
            f"`ddyn export {ckpt_path} --out DIR`, then `bash scripts/build.sh {Path(tool).parents[1]} "
            f"-DDDYN_NET_EXPORT_DIR=DIR` (the main job builds build/ for its checkpoint; the test command "
            f"builds build-test/ for the fixture network)")
    return built
