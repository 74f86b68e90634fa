"""Build the Blender extension zip: `make blender-addon`, or

    python blender/build_extension.py [--out build]

writes `build/quietframe-blender-<version>.zip` (the version from blender_manifest.toml) with the
add-on's files at the zip's root, as Blender installs an extension (Edit > Preferences > Get
Extensions > Install from Disk), and quietframe's `wire/` package copied in as `_wire/`: an
installed extension is self-contained, and the add-on imports the protocol and the EXR header
reader from there (quietframe_blender/wire.py) rather than keeping copies of its own.

`wire/` imports nothing but the standard library and never itself by its absolute name
(quietframe.wire), so it works unchanged under another package's name; this script checks that
before it bundles it, and fails rather than ship a copy that would import what the zip lacks.
The zip is reproducible: sorted entries, fixed timestamps, no byte code.
"""

from __future__ import annotations

import argparse
import ast
import re
import sys
import zipfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
ADDON = ROOT / "blender" / "quietframe_blender"
WIRE = ROOT / "wire"
BUNDLED_WIRE = "_wire"
_STAMP = (2026, 1, 1, 0, 0, 0)


def manifest_version(manifest: Path) -> str:
    match = re.search(r'^version\s*=\s*"([^"]+)"', manifest.read_text(), re.MULTILINE)
    if match is None:
        raise SystemExit(f"{manifest} has no version line")
    return match[1]


def addon_files() -> list[tuple[Path, str]]:
    """(file, name in the zip) of the add-on's own files."""
    files = []
    for path in sorted(ADDON.rglob("*")):
        relative = path.relative_to(ADDON)
        if (path.is_dir() or "__pycache__" in relative.parts or path.suffix == ".pyc"
                or relative.parts[0] == BUNDLED_WIRE):
            continue
        files.append((path, relative.as_posix()))
    return files


def wire_files() -> list[tuple[Path, str]]:
    """(file, name in the zip) of wire/'s modules, each checked to import only the standard
    library and its own package relatively."""
    files = []
    for path in sorted(WIRE.glob("*.py")):
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            names = []
            if isinstance(node, ast.Import):
                names = [alias.name for alias in node.names]
            elif isinstance(node, ast.ImportFrom) and node.level == 0:
                names = [node.module or ""]
            for name in names:
                top = name.split(".")[0]
                if top not in sys.stdlib_module_names and top != "__future__":
                    raise SystemExit(
                        f"{path.relative_to(ROOT)} imports {name}: the bundled copy "
                        "(_wire/) can hold only modules that import the standard library "
                        "and each other relatively"
                    )
        files.append((path, f"{BUNDLED_WIRE}/{path.name}"))
    return files


def build(out_dir: Path) -> Path:
    version = manifest_version(ADDON / "blender_manifest.toml")
    out_dir.mkdir(parents=True, exist_ok=True)
    target = out_dir / f"quietframe-blender-{version}.zip"
    partial = target.with_name(target.name + ".part")
    with zipfile.ZipFile(partial, "w", zipfile.ZIP_DEFLATED) as archive:
        for path, name in sorted(addon_files() + wire_files(), key=lambda item: item[1]):
            info = zipfile.ZipInfo(name, _STAMP)
            info.compress_type = zipfile.ZIP_DEFLATED
            info.external_attr = 0o644 << 16
            archive.writestr(info, path.read_bytes())
    partial.replace(target)
    return target


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=ROOT / "build",
                        help="folder for the zip (default: build/)")
    args = parser.parse_args(argv)
    print(build(args.out))


if __name__ == "__main__":
    main()
