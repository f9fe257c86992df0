"""Where a volume lives when it is not a local file: an fsspec URL of a store (an OME-Zarr pyramid on a web server,
in a bucket or a zip), which ``--volume`` and `volren.load` take as they take a path (issue 41 item 3)."""

from __future__ import annotations

from pathlib import Path


class StoreURL(str):
    """An fsspec URL (``https://host/image.zarr``, ``s3://bucket/a.zarr``, ``zip::file:///data/a.zarr.zip``) where
    a `Path` names a local file: its name, stem and suffix read as a path's, and it is no local file or folder."""

    @property
    def name(self) -> str:
        return self.rstrip("/").rsplit("/", 1)[-1]

    @property
    def stem(self) -> str:
        return Path(self.name).stem

    @property
    def suffix(self) -> str:
        return Path(self.name).suffix

    def is_dir(self) -> bool:
        return False

    def is_file(self) -> bool:
        return False


def volume_path(text: str) -> Path | StoreURL:
    """``--volume``'s value: a URL (it holds ``://``) as a `StoreURL`, anything else a local `Path`."""
    return StoreURL(text) if "://" in text else Path(text)
