"""The sections of the HTML report about the run itself (`svolsdf.evaluate.report`): what made
it (command, version, device, date: OUT/run.json), the optimization's loss curves
(field/losses.csv), a chart of the stage times (timing.json) and the config, collapsed."""

from __future__ import annotations

import base64
import csv
import html
import io
import logging
import math
from pathlib import Path

from svolsdf.errors import raise_if_interrupted
from svolsdf.evaluate.report_parts import figure

__all__ = ["config_section", "loss_curves_section", "read_losses", "run_section",
           "stage_time_section"]

log = logging.getLogger(__name__)

_LOSS_KEYS = ("total", "rgb", "eikonal", "mvs", "sparse")
"""The curves drawn, when the log has them (losses.csv has more columns: beta, steps_per_s)."""


def read_losses(path: Path) -> list[dict[str, float]]:
    """The rows of a trainer's losses.csv (`svolsdf.optimize.Trainer.write_log`) as numbers;
    [] when the file is missing or unreadable (the report says so)."""
    try:
        with open(path, newline="") as f:
            rows = list(csv.DictReader(f))
    except (OSError, UnicodeDecodeError, csv.Error):
        return []
    out = []
    for r in rows:
        try:
            out.append({k: float(v) for k, v in r.items() if k and v not in (None, "")})
        except ValueError:
            continue
    return [r for r in out if "step" in r]


def _chart(draw, width: float = 7.0, height: float = 3.2) -> str | None:
    """A matplotlib figure made by ``draw(ax)`` as a base64 PNG; None when plotting fails."""
    try:
        import matplotlib

        matplotlib.use("Agg", force=False)
        import matplotlib.pyplot as plt

        fig, ax = plt.subplots(figsize=(width, height))
        try:
            draw(ax)
            fig.tight_layout()
            buf = io.BytesIO()
            fig.savefig(buf, format="png", dpi=90)
        finally:
            plt.close(fig)
        return base64.b64encode(buf.getvalue()).decode("ascii")
    except Exception as e:  # a chart is a convenience: never fail the report on it
        raise_if_interrupted()
        log.warning("report: chart not drawn (%s)", e)
        return None


def run_section(info: dict | None, config_text: str | None) -> str:
    """Command, version, device and date of the run (OUT/run.json, written when a
    reconstruction finishes), and the device its config asked for."""
    info = info or {}
    device_asked = None
    if config_text:
        import yaml

        try:
            device_asked = (yaml.safe_load(config_text) or {}).get("device")
        except yaml.YAMLError:
            device_asked = None
    rows = [("command", info.get("command")), ("svolsdf version", info.get("version")),
            ("device", info.get("device") or (f"{device_asked} (asked for; run.json not "
                                              "recorded)" if device_asked else None)),
            ("torch", info.get("torch")), ("date (UTC)", info.get("date"))]
    body = "".join(f"<tr><td>{html.escape(k)}</td><td class='val'>"
                   f"{html.escape(str(v)) if v is not None else 'not recorded'}</td></tr>"
                   for k, v in rows)
    note = "" if info else ("<p>No run.json: the run finished before the report recorded "
                            "what made it, or was not made by svolsdf reconstruct.</p>")
    return f"<h2>Run</h2>{note}<table id='run'><tbody>{body}</tbody></table>"


def loss_curves_section(curves: dict[str, list[dict[str, float]]]) -> str:
    """The optimization's losses against the step, one chart per optimization (the field; the
    finer-stage one when it ran), log scale."""
    figs = []
    for name, rows in curves.items():
        if not rows:
            continue
        keys = [k for k in _LOSS_KEYS if any(k in r for r in rows)]

        def draw(ax, rows=rows, keys=keys, name=name):
            steps = [r["step"] for r in rows]
            for k in keys:
                ys = [r.get(k, math.nan) for r in rows]
                ax.plot(steps, [y if y > 0 else math.nan for y in ys], label=k)
            ax.set_yscale("log")
            ax.set_xlabel("step")
            ax.set_ylabel("loss")
            ax.set_title(name, fontsize=10)
            ax.legend(fontsize=8)
            ax.grid(alpha=0.3)

        b64 = _chart(draw)
        if b64 is not None:
            figs.append(figure(b64, f"loss curves: {name} ({len(rows)} logged steps)"))
    if not figs:
        return ""
    return ("<h2>Loss curves</h2><p>The losses logged during the optimization (losses.csv; "
            "with the tensorboard extra also live: tensorboard --logdir OUT/field).</p>"
            f"<div class='grid charts'>{''.join(figs)}</div>")


def stage_time_section(timing: dict | None) -> str:
    """A horizontal bar per stage of its seconds (timing.json), the total in the caption."""
    stages = [(k, float(v["seconds"])) for k, v in (timing or {}).items()
              if isinstance(v, dict) and isinstance(v.get("seconds"), (int, float))
              and k != "total"]
    if not stages:
        return ""
    total = ((timing or {}).get("total") or {}).get("seconds")

    def draw(ax):
        names = [k for k, _ in stages][::-1]
        secs = [s for _, s in stages][::-1]
        ax.barh(names, secs, color="#4c72b0")
        for y, s in enumerate(secs):
            ax.text(s, y, f" {s:.1f}", va="center", fontsize=8)
        ax.set_xlabel("seconds")
        ax.grid(axis="x", alpha=0.3)

    b64 = _chart(draw, height=0.35 * len(stages) + 1.0)
    if b64 is None:
        return ""
    cap = "time per stage (timing.json)" + (f"; total {total:.1f} s" if total else "")
    return f"<h2>Stage times</h2>{figure(b64, cap)}"


def config_section(config_text: str | None) -> str:
    """The run's config.yaml, collapsed (a click opens it)."""
    if not config_text:
        return ""
    return ("<h2>Run configuration</h2><details id='config'><summary>config.yaml "
            f"({len(config_text.splitlines())} lines; click to open)</summary>"
            f"<pre>{html.escape(config_text)}</pre></details>")
