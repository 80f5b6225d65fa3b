"""The package data: what an installed companion (no repository around it) runs on.

``companion/data`` holds the embedded default (``default.yaml``), the bundled
sequence it replays and, as a link to the top-level ``maps/warehouse.yaml`` (one
copy of the file), the example map; an sdist or wheel holds the content.
`.ci/run` builds and runs the real wheel; here a copy of the package with the
link replaced by its content stands in for it.
"""
from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
DATA = REPO / "companion" / "data"
LINKED = {"maps/warehouse.yaml"}

# Loads the embedded default and prints what it found, as JSON.
PROBE = """
import json
import companion
from companion.daemon.config import default_config_path, load_config
config = load_config()
print(json.dumps({"package": companion.__file__, "config": str(default_config_path()),
                  "sequence": str(config.source.path.resolve()), "map": str(config.facility_map.path),
                  "width_px": config.camera.width, "markers": len(config.facility_map.markers)}))
"""


def test_package_data_links_to_the_one_copy_of_the_map_in_the_repository():
    links = {p.relative_to(DATA).as_posix(): p for p in DATA.rglob("*") if p.is_symlink()}
    assert set(links) == LINKED
    for relative, link in links.items():
        top = REPO / relative
        assert top.exists() and not top.is_symlink(), relative
        assert link.resolve() == top.resolve(), relative


def test_embedded_default_loads_from_the_package_alone(tmp_path):
    site = tmp_path / "site"
    # as setuptools copies package data: links followed, their content copied
    shutil.copytree(REPO / "companion", site / "companion", symlinks=False,
                    ignore=shutil.ignore_patterns("__pycache__"))
    result = subprocess.run([sys.executable, "-c", PROBE], cwd=tmp_path, capture_output=True, text=True,
                            env={**os.environ, "PYTHONPATH": str(site)}, timeout=60)
    assert result.returncode == 0, result.stderr
    found = json.loads(result.stdout)
    package = site / "companion"
    assert Path(found["package"]).parent == package  # not the repository's
    assert Path(found["config"]) == package / "data" / "default.yaml"
    assert Path(found["sequence"]) == package / "data" / "sequences" / "warehouse_aisle"
    assert Path(found["map"]).resolve() == package / "data" / "maps" / "warehouse.yaml"
    # the sequence's own camera (sequence.yaml: 640 x 480) and the map's 49 markers (maps/warehouse.yaml)
    assert found["width_px"] == 640 and found["markers"] == 49
