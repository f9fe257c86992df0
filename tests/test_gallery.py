"""scripts/gallery.py: every built-in scene by default, rendered as `volren render` would, and a contact sheet."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np
from PIL import Image

ROOT = Path(__file__).resolve().parent.parent


def _gallery():
    spec = importlib.util.spec_from_file_location("gallery", ROOT / "scripts" / "gallery.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_gallery_lists_every_scene_of_volren_scenes(capsys):
    from volren.cli import main

    main(["scenes"])
    listed = [line.split()[0] for line in capsys.readouterr().out.splitlines() if line.strip()]
    assert _gallery().all_scenes() == listed


def test_gallery_renders_tiles_and_a_contact_sheet_at_a_tiny_size(tmp_path):
    gallery = _gallery()
    out = tmp_path / "gallery"
    assert gallery.main(["--out", str(out), "--scenes", "cloud,courtyard", "--width", "32", "--height", "24",
                         "--resolution", "64", "--device", "cpu"]) == 0
    tiles = [np.asarray(Image.open(out / f"{name}.png").convert("RGB"), dtype=float) for name in ("cloud", "courtyard")]
    assert all(t.shape == (24, 32, 3) and t.std() > 1.0 for t in tiles)  # something drawn in each
    sheet = np.asarray(Image.open(tmp_path / "gallery.png").convert("RGB"), dtype=float)
    assert sheet.shape == (24 + gallery.LABEL, gallery.COLUMNS * 32, 3)
    np.testing.assert_array_equal(sheet[gallery.LABEL :, 32:64], tiles[1])  # the second tile, under its label
