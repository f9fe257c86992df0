"""Benchmarks: one suite per table of the papers. Each writes JSON (machine, device, settings, figures) and a
Markdown table. ``--quick`` sizes run on a CPU in seconds; full sizes are for a GPU."""

from __future__ import annotations

import json
import os
import platform
from collections.abc import Callable
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import warp as wp

from volren.device import cpu_threads, resolve_device
from volren.errors import VolrenError


@dataclass(frozen=True)
class Suite:
    name: str
    description: str
    run: Callable[[bool, str], dict[str, Any]]
    """(quick, device) -> {"settings": ..., "rows": [dict, ...], "columns": [(key, header, format), ...]}"""


def all_suites() -> dict[str, Suite]:
    """Every suite by name (imported here, so importing volren.bench stays cheap)."""
    from volren.bench.dssrm import SUITE as DSSRM_SUITE

    return {s.name: s for s in (DSSRM_SUITE,)}


def machine_info(device: str) -> dict[str, Any]:
    cpu = platform.processor()
    try:
        with open("/proc/cpuinfo") as f:
            cpu = next((line.split(":", 1)[1].strip() for line in f if line.startswith("model name")), cpu)
    except OSError:
        pass
    return {
        "hostname": platform.node(),
        "cpu": cpu,
        "cpu_count": os.cpu_count(),
        "cpu_threads_used": cpu_threads(),
        "device": device,
        "device_name": wp.get_device(device).name,
        "python": platform.python_version(),
        "warp": wp.__version__,
        "date": datetime.now(UTC).isoformat(timespec="seconds"),
    }


def markdown_table(rows: list[dict[str, Any]], columns: list[tuple[str, str, str]]) -> str:
    head = "| " + " | ".join(h for _, h, _ in columns) + " |"
    rule = "| " + " | ".join("---" for _ in columns) + " |"
    body = ["| " + " | ".join(format(r[k], f) if r.get(k) is not None else "" for k, _, f in columns) + " |"
            for r in rows]
    return "\n".join([head, rule, *body])


def run_suite(name: str, *, quick: bool, device: str, out: Path) -> tuple[Path, Path, str]:
    suites = all_suites()
    if name not in suites:
        raise VolrenError(f"unknown bench suite '{name}': choose from {', '.join(suites)}")
    device = resolve_device(device)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise VolrenError(f"cannot create '{out}': {exc.strerror}") from exc
    result = suites[name].run(quick, device)
    doc = {"suite": name, "quick": quick, "machine": machine_info(device), **result}
    tag = f"{name}-{'cpu' if device == 'cpu' else 'cuda'}-{'quick' if quick else 'full'}"
    json_path, md_path = out / f"{tag}.json", out / f"{tag}.md"
    json_path.write_text(json.dumps(doc, indent=2, default=str) + "\n")
    m = doc["machine"]
    table = markdown_table(result["rows"], result["columns"])
    md_path.write_text(f"### {name} ({'quick' if quick else 'full'}) on {m['device_name']} ({m['cpu']}, "
                       f"{m['cpu_threads_used']} CPU threads), warp {m['warp']}, {m['date']}\n\n{table}\n")
    return json_path, md_path, table
