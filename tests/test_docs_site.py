"""The documentation site (issue 42 item 4): `mkdocs build --strict` of docs/ succeeds offline, and a broken
relative link or anchor between the pages fails it (mkdocs.yml's `validation`), as `make docs` runs it in CI."""

from __future__ import annotations

import importlib.util
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

if importlib.util.find_spec("mkdocs") is None or importlib.util.find_spec("material") is None:
    if os.environ.get("CI") == "true":
        pytest.fail("mkdocs-material is missing in CI: `make test` installs the docs extra", pytrace=False)
    pytest.skip("mkdocs-material is a docs extra (pip install -e '.[docs]')", allow_module_level=True)


def build(config: Path, site: Path) -> subprocess.CompletedProcess:
    env = {**os.environ, "NO_MKDOCS_2_WARNING": "1"}
    return subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "-f", str(config), "-d", str(site)],
                          capture_output=True, text=True, env=env, timeout=120)


def copy_of_the_site(folder: Path) -> Path:
    """mkdocs.yml and docs/ copied into ``folder`` (the API pages still read ../src); returns the config's path."""
    shutil.copytree(ROOT / "docs", folder / "docs")
    config = (ROOT / "mkdocs.yml").read_text().replace("paths: [src]", f"paths: [{ROOT / 'src'}]")
    assert str(ROOT / "src") in config
    (folder / "mkdocs.yml").write_text(config)
    return folder / "mkdocs.yml"


@pytest.mark.timeout(120)
def test_the_site_builds_strictly_with_every_page(tmp_path):
    done = build(ROOT / "mkdocs.yml", tmp_path / "site")
    assert done.returncode == 0, done.stderr[-3000:]
    site = tmp_path / "site"
    for page in ("index.html", "API/index.html", "CLI/index.html", "SERVE/index.html", "BENCHMARKS/index.html",
                 "BENCHMARKS-LOG/index.html", "gallery/index.html"):
        assert (site / page).is_file(), page
    api = (site / "API" / "index.html").read_text()
    public = ("load", "render", "builtin_scene", "views", "Renderer", "Scene", "Volume", "Camera", "Frame", "Viewer")
    for name in public:
        assert re.search(rf'id="volren\.[\w.]*\b{name}"', api), f"the API page lacks {name}"
    assert "placed in the world as it places it" in api  # vr.load's docstring, read by mkdocstrings
    assert (site / "figures" / "gallery" / "smoke.png").is_file()
    assert "fonts.googleapis.com" not in (site / "index.html").read_text()  # theme.font: false, nothing fetched


BROKEN = {
    "[the claims](BENCHMARKS.md#no-such-section)": "does not contain an anchor '#no-such-section'",
    "[a page](no-such-page.md)": "'no-such-page.md', but the target is not found",
    "[a script](../scripts/gallery.py)": "'../scripts/gallery.py', but the target is not found",
}
"""a broken anchor, a missing page and a link out of docs/ (GitHub would show the file, the site has none)"""


@pytest.mark.timeout(120)
def test_a_broken_link_fails_the_strict_build(tmp_path):
    config = copy_of_the_site(tmp_path)
    index = tmp_path / "docs" / "index.md"
    index.write_text(index.read_text() + "".join(f"\n{link}\n" for link in BROKEN))
    done = build(config, tmp_path / "site")
    assert done.returncode != 0, done.stderr[-3000:]
    warned = [line for line in done.stderr.splitlines() if line.startswith("WARNING")]
    missed = [link for link, says in BROKEN.items() if not any(says in line for line in warned)]
    assert not missed, f"not warned of (each alone fails the strict build): {missed}\n{done.stderr[-3000:]}"


def test_the_gallery_page_shows_every_built_in_scene():
    spec = importlib.util.spec_from_file_location("gallery", ROOT / "scripts" / "gallery.py")
    gallery = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(gallery)
    page = (ROOT / "docs" / "gallery.md").read_text()
    assert "python scripts/gallery.py --out docs/figures/gallery" in page
    for scene in gallery.all_scenes():
        assert f"(figures/gallery/{scene}.png)" in page, scene
        assert (ROOT / "docs" / "figures" / "gallery" / f"{scene}.png").is_file(), scene


def test_every_page_of_docs_is_in_the_nav():
    config = (ROOT / "mkdocs.yml").read_text()
    pages = sorted(p.name for p in (ROOT / "docs").glob("*.md"))
    assert pages and all(f": {page}" in config for page in pages), pages


def test_the_readmes_links_into_docs_find_their_page_and_anchor():
    """README.md is outside the site: its links into docs/ are checked here, anchors by the site's own slugs
    (GitHub's), so a section renamed or moved to the log fails."""
    from pymdownx.slugs import slugify

    slug = slugify(case="lower")
    readme = (ROOT / "README.md").read_text()
    links = re.findall(r"\]\((docs/[^)#\s]+)(?:#([^)\s]+))?\)", readme)
    assert any(anchor for _, anchor in links)
    for path, anchor in links:
        assert (ROOT / path).exists(), path
        if anchor:
            headings = re.findall(r"^#{1,6} (.+)$", (ROOT / path).read_text(), flags=re.M)
            assert anchor in {slug(h.replace("`", ""), "-") for h in headings}, f"{path}#{anchor}"
