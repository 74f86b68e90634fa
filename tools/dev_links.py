"""Link the source folders into site-packages as quietframe.<folder> (development only)."""

import site
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
FOLDERS = [
    "model", "scenes", "export", "runtime", "service", "client", "wire", "bench", "experiments",
    "models",
]

target = Path(site.getsitepackages()[0]) / "quietframe"
target.mkdir(exist_ok=True)
for name in FOLDERS:
    link = target / name
    if link.is_symlink() or link.exists():
        if link.is_symlink():
            link.unlink()
        else:
            continue
    link.symlink_to(ROOT / name, target_is_directory=True)
print(f"linked {len(FOLDERS)} folders into {target}")
