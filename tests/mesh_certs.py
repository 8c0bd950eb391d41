"""docs/service.md's "Two routers with certificates", as a user follows it: its openssl commands run in a folder of
the test's, and the shipped deploy/multihost files with that folder and the routers' host names substituted."""

from __future__ import annotations

import re
import subprocess
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
MULTIHOST = REPO / "deploy" / "multihost"


def recipe_block(n: int) -> str:
    """The n-th bash block of the recipe."""
    text = (REPO / "docs" / "service.md").read_text()
    section = text.split("### Two routers with certificates", 1)[1].split("\n## ", 1)[0]
    return re.findall(r"```bash\n(.*?)```", section, re.S)[n]


def as_user(text: str, tls: Path) -> str:
    """What the recipe tells a user to edit: the certificates' folder and the routers' host names (loopback here)."""
    text = text.replace("/etc/occvo/tls", str(tls))
    return text.replace("occvo-router-a.lan", "localhost").replace("occvo-router-b.lan", "localhost")


def make_certificates(tls: Path, logins: tuple[str, ...] = ()) -> None:
    """The recipe's certificates in `tls`, and one for each further client login in `logins`."""
    script = as_user(recipe_block(0), tls).replace(" map camera;", " ".join([" map camera", *logins]) + ";")
    subprocess.run(["bash", "-euc", script], check=True, capture_output=True, timeout=120)


def shipped(name: str, folder: Path, tls: Path) -> Path:
    """deploy/multihost/<name> as the user's copy in `folder`."""
    out = folder / name
    out.write_text(as_user((MULTIHOST / name).read_text(), tls))
    return out
