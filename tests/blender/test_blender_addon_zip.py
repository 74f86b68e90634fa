"""The extension zip `make blender-addon` builds (blender/build_extension.py): Blender's layout
(the manifest and the add-on at the zip's root), a manifest with the keys Blender requires, the
wire package bundled as `_wire/` and used from there, and nothing bundled that would import
what the zip lacks."""

from __future__ import annotations

import importlib
import sys
import zipfile

import pytest
import tomllib
from blender_addon_support import ROOT, extension_builder

build_extension = extension_builder()

WIRE_MODULES = sorted(p.name for p in (ROOT / "wire").glob("*.py"))


@pytest.fixture(scope="module")
def built(tmp_path_factory):
    return build_extension.build(tmp_path_factory.mktemp("dist"))


def test_the_zip_holds_the_manifest_the_addon_and_the_wire_package(built):
    with zipfile.ZipFile(built) as archive:
        names = set(archive.namelist())
        for module in WIRE_MODULES:  # byte for byte the repository's wire/
            assert archive.read(f"_wire/{module}") == (ROOT / "wire" / module).read_bytes()
    addon = ROOT / "blender" / "quietframe_blender"
    own = {p.relative_to(addon).as_posix() for p in addon.rglob("*")
           if p.is_file() and "__pycache__" not in p.parts}
    assert names == own | {f"_wire/{m}" for m in WIRE_MODULES}
    assert {"blender_manifest.toml", "__init__.py", "_wire/protocol.py",
            "_wire/exr_layout.py"} <= names


def test_the_manifest_has_what_blender_requires(built):
    with zipfile.ZipFile(built) as archive:
        manifest = tomllib.loads(archive.read("blender_manifest.toml").decode())
    assert manifest["schema_version"] == "1.0.0"
    assert manifest["id"] == "quietframe" and manifest["type"] == "add-on"
    assert built.name == f"quietframe-blender-{manifest['version']}.zip"
    assert manifest["blender_version_min"] == "4.2.0"
    assert manifest["license"] == ["SPDX:Apache-2.0"]
    assert manifest["name"] and manifest["maintainer"]
    tagline = manifest["tagline"]
    assert 0 < len(tagline) <= 64 and tagline[-1].isalnum()  # Blender's rule: no end punctuation
    assert set(manifest["permissions"]) == {"network", "files"}
    assert all(reason and reason[-1].isalnum() for reason in manifest["permissions"].values())


def test_the_unpacked_addon_imports_the_bundled_wire(built, tmp_path):
    package = tmp_path / "unpacked_quietframe"
    with zipfile.ZipFile(built) as archive:
        archive.extractall(package)
    sys.path.insert(0, str(tmp_path))
    try:
        wire = importlib.import_module("unpacked_quietframe.wire")
        job = importlib.import_module("unpacked_quietframe.denoise_job")  # no bpy needed
        assert wire.protocol.__name__ == "unpacked_quietframe._wire.protocol"
        assert wire.exr_layout.__name__ == "unpacked_quietframe._wire.exr_layout"
        assert job.frame_files.exr_layout is wire.exr_layout
        assert "bpy" not in sys.modules
    finally:
        sys.path.remove(str(tmp_path))
        for name in [n for n in sys.modules if n.startswith("unpacked_quietframe")]:
            del sys.modules[name]


def test_the_build_is_reproducible(built, tmp_path):
    assert build_extension.build(tmp_path).read_bytes() == built.read_bytes()


@pytest.mark.parametrize("line", ["from quietframe.wire import protocol", "import numpy"])
def test_a_wire_module_importing_beyond_the_standard_library_is_not_bundled(
        tmp_path, monkeypatch, line):
    wire = tmp_path / "wire"
    wire.mkdir()
    (wire / "__init__.py").write_text("")
    (wire / "protocol.py").write_text(f"from __future__ import annotations\n{line}\n")
    monkeypatch.setattr(build_extension, "WIRE", wire)
    monkeypatch.setattr(build_extension, "ROOT", tmp_path)
    with pytest.raises(SystemExit, match=f"wire/protocol.py imports {line.split()[1]}"):
        build_extension.build(tmp_path / "dist")
    assert not list((tmp_path / "dist").glob("*.zip"))
