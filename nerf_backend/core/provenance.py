"""What produced a benchmark's figures: the command as typed and the source's commit, written
into its tables so that a number quoted in the docs can be traced and made again.

>>> record = provenance("python -m nerf_backend bench D --out B")
>>> sorted(record), record["command"]
(['command', 'commit'], 'python -m nerf_backend bench D --out B')
>>> provenance_line({"command": "python -m nerf_backend bench D", "commit": "1a2b3c4+changes"})
'Made by `python -m nerf_backend bench D` at commit 1a2b3c4+changes.'
"""

from __future__ import annotations

import subprocess
from pathlib import Path

SOURCE_ROOT = Path(__file__).resolve().parents[2]


def source_commit(root: Path = SOURCE_ROOT) -> str | None:
    """The checkout's short commit, with '+changes' when tracked files differ from it; None
    outside a git checkout (an installed extension, a copied folder)."""
    if not (root / ".git").exists():
        return None
    try:
        head = subprocess.run(["git", "-C", str(root), "rev-parse", "--short=7", "HEAD"], capture_output=True,
                              text=True, timeout=30)
        status = subprocess.run(["git", "-C", str(root), "status", "--porcelain", "--untracked-files=no"],
                                capture_output=True, text=True, timeout=30)
    except (OSError, subprocess.TimeoutExpired):
        return None
    if head.returncode != 0:
        return None
    return head.stdout.strip() + ("+changes" if status.stdout.strip() else "")


def provenance(command: str | None) -> dict:
    """``{"command", "commit"}`` for a report (``command`` None where a function was called
    directly rather than from the command line)."""
    return {"command": command, "commit": source_commit()}


def provenance_line(record: dict | None) -> str:
    """The sentence a table starts with; '' when nothing is known."""
    if not record or not (record.get("command") or record.get("commit")):
        return ""
    made = f"Made by `{record['command']}`" if record.get("command") else "Made"
    return f"{made} at commit {record.get('commit') or 'unknown (not a git checkout)'}."
