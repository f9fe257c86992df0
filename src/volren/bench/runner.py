"""Running a suite (``volren bench NAME``): the registry of every suite and the run that writes its JSON and
Markdown. Its own module, so the package's toolkit (`Suite`, `measure`, `sized`, ...) that every suite imports does not
import the suites back."""

from __future__ import annotations

import json
import os
import time
from pathlib import Path
from typing import Any

from volren.bench import DEFAULT_OUT, OVERRIDES, REPEATS, Suite, machine_info, markdown_table
from volren.device import resolve_device
from volren.errors import VolrenError
from volren.progress import cases


def all_suites() -> dict[str, Suite]:
    """Every suite by name (imported here, so importing volren.bench stays cheap)."""
    from volren.bench.batch import SUITE as BATCH_SUITE
    from volren.bench.bigdata import SUITE as BIGDATA_SUITE
    from volren.bench.binocular import SUITE as BINOCULAR_SUITE
    from volren.bench.bricks import SUITE as BRICKS_SUITE
    from volren.bench.dataparallel import SUITE as DATAPARALLEL_SUITE
    from volren.bench.dssrm import SUITE as DSSRM_SUITE
    from volren.bench.gi import SUITE as GI_SUITE
    from volren.bench.integrated import SUITE as INTEGRATED_SUITE
    from volren.bench.interactive import SUITE as INTERACTIVE_SUITE
    from volren.bench.load import SUITE as LOAD_SUITE
    from volren.bench.oit import SUITE as OIT_SUITE
    from volren.bench.peers import SUITE as PEERS_SUITE
    from volren.bench.resolution import SUITE as RESOLUTION_SUITE
    from volren.bench.serve import SUITE as SERVE_SUITE
    from volren.bench.viewers import SUITE as VIEWERS_SUITE
    from volren.bench.vpt import SUITE as VPT_SUITE

    return {s.name: s for s in (DSSRM_SUITE, RESOLUTION_SUITE, BINOCULAR_SUITE, VIEWERS_SUITE, VPT_SUITE, GI_SUITE,
                                OIT_SUITE, INTEGRATED_SUITE, SERVE_SUITE, INTERACTIVE_SUITE, LOAD_SUITE, PEERS_SUITE,
                                BATCH_SUITE, BRICKS_SUITE, BIGDATA_SUITE, DATAPARALLEL_SUITE)}



def run_suite(name: str, *, quick: bool, device: str, out: Path | None = None,
              suite: Suite | None = None, repeats: int | None = None,
              overrides: dict[str, Any] | None = None) -> tuple[Path, Path, str]:
    """Run suite ``name`` and write ``<name>-<cpu|cuda>-<quick|full>.{json,md}`` into ``out`` (default
    :data:`DEFAULT_OUT`); each file is written beside its name and renamed over it, so a failure leaves the old one.
    ``suite``: run that one under ``name`` (a suite with options bound: ``bench serve --shards``). ``repeats``: timed
    frames per case instead of the suite's own (suites timed by `measure` only; recorded in the JSON's settings).
    ``overrides``: configuration entries replaced (`sized`; recorded as the settings' "overridden" keys)."""
    out = DEFAULT_OUT if out is None else out
    suites = all_suites() if suite is None else {name: suite}
    if name not in suites:
        raise VolrenError(f"unknown bench suite '{name}': choose from {', '.join(suites)}")
    if repeats is not None:
        takes = [n for n, s in all_suites().items() if s.repeats]
        if not suites[name].repeats:
            raise VolrenError(f"--repeats: bench {name} times its work its own way; it applies to "
                              f"{', '.join(takes)}")
        if repeats < 1:
            raise VolrenError(f"--repeats must be at least 1, got {repeats}")
    if overrides and not suites[name].settable:
        takes = [n for n, s in all_suites().items() if s.settable]
        raise VolrenError(f"--set: bench {name} has no settings to change; it applies to {', '.join(takes)}")
    device = resolve_device(device)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise VolrenError(f"cannot create '{out}': {exc.strerror}") from exc
    start = time.perf_counter()
    token, changed = REPEATS.set(repeats), OVERRIDES.set(dict(overrides or {}))
    try:
        with cases(f"bench {name}"):  # a line per measured case on stderr: a suite takes minutes
            result = suites[name].run(quick, device)
    finally:
        REPEATS.reset(token)
        OVERRIDES.reset(changed)
    elapsed = time.perf_counter() - start
    if repeats is not None:
        result["settings"] = {**result.get("settings", {}), "repeats": repeats, "repeats_cut_from_suite": True}
    if overrides:
        result["settings"] = {**result.get("settings", {}), "overridden": sorted(overrides)}
    table = markdown_table(result["rows"], result["columns"])
    summary_rows, summary_columns = result.pop("summary", ([], []))
    if summary_rows:
        table += "\n\n" + markdown_table(summary_rows, summary_columns)
    notes = result.pop("notes", {})  # Markdown a suite writes before one of its further tables, by its key
    for key, more_columns in result.pop("more_tables", {}).items():  # further tables: rows kept under ``key``
        if result.get(key):
            table += (f"\n\n{notes[key]}" if key in notes else "") + "\n\n" + markdown_table(result[key], more_columns)
    doc = {"suite": name, "quick": quick, "machine": machine_info(device), "elapsed_s": round(elapsed, 1), **result,
           "summary": summary_rows}
    tag = f"{name}-{'cpu' if device == 'cpu' else 'cuda'}-{'quick' if quick else 'full'}"
    json_path, md_path = out / f"{tag}.json", out / f"{tag}.md"
    m = doc["machine"]
    from volren.imageio import save_srgb8

    for file, pixels in doc.pop("figures", {}).items():  # images a suite shows beside its table (uint8 sRGB)
        save_srgb8(out / f"{tag}-{file}", pixels)
        table += f"\n\n![{file}]({tag}-{file})"
    _write_replace(json_path, json.dumps(doc, indent=2, default=str) + "\n")
    _write_replace(md_path, f"### {name} ({'quick' if quick else 'full'}) on {m['device_name']} ({m['cpu']}, "
                            f"{m['cpu_threads_used']} CPU threads), warp {m['warp']}, {m['date']}, "
                            f"{elapsed / 60:.1f} min"
                            f"{f', {repeats} timed frame(s) per case' if repeats else ''}"
                            f"{''.join(f', {k} = {v}' for k, v in (overrides or {}).items())}\n\n{table}\n")
    return json_path, md_path, table


def _write_replace(path: Path, text: str) -> None:
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_text(text)
    os.replace(tmp, path)
