"""The tables and the chart of ``svolsdf benchmark`` (`svolsdf.commands.benchmark`), from its
per-run rows: a Markdown table like the paper's Table 1, the same as CSV, and a bar chart.

Functions of the rows alone (dicts with ``scene``, ``mode`` and the numeric keys of
`svolsdf.commands.benchmark.METRIC_KEYS`): they run nothing and read no run folder;
`benchmark_plot` writes the one file it is given.
"""
from __future__ import annotations

import csv
import io
import math
from pathlib import Path

from svolsdf.errors import InputError

__all__ = [
    "benchmark_csv",
    "benchmark_markdown",
    "benchmark_plot",
    "method_label",
    "protocol_groups",
]


def method_label(mode: str, field_kind: str | None = None) -> str:
    """What a run of ``mode`` (``cfg.train.mode``) with a field of ``field_kind``
    (``cfg.field.kind``; None: not recorded) is, for tables: ``--mode volsdf`` is the paper's
    VolSDF only with the MLP; with the grid field it is the same fast field without the MVS
    prior, which a table must not call VolSDF."""
    if mode == "volsdf":
        return {"grid": "VolSDF (grid field, no prior)", "mlp": "VolSDF (MLP)"}.get(
            field_kind, "VolSDF (field kind not recorded)")
    if mode == "svolsdf":
        return {"grid": "S-VolSDF", "mlp": "S-VolSDF (MLP)"}.get(field_kind, "S-VolSDF")
    return {"mvs-only": "MVS only"}.get(mode, mode)


def _mode_labels(rows: list[dict], modes: list[str]) -> dict[str, str]:
    """mode -> its method label(s) from the rows' ``field`` kinds ("a / b" when they differ)."""
    out = {}
    for m in modes:
        kinds = list(dict.fromkeys(r.get("field") for r in rows if r["mode"] == m))
        out[m] = " / ".join(method_label(m, k) for k in kinds or [None])
    return out


# --------------------------------------------------------------------------- tables
def _fmt(x, digits: int) -> str:
    return "-" if x is None or not math.isfinite(x) else f"{x:.{digits}f}"


def _mean(values: list) -> float | None:
    vs = [float(v) for v in values if v is not None and math.isfinite(float(v))]
    return sum(vs) / len(vs) if vs else None


def _grid(rows: list[dict], modes: list[str] | None) -> tuple[list[str], list[str], dict]:
    """Scenes (first-seen order), modes and {(scene, mode): row}."""
    scenes: list[str] = []
    seen_modes: list[str] = []
    cell = {}
    for r in rows:
        if r["scene"] not in scenes:
            scenes.append(r["scene"])
        if r["mode"] not in seen_modes:
            seen_modes.append(r["mode"])
        cell[(r["scene"], r["mode"])] = r
    return scenes, list(modes) if modes else seen_modes, cell


def _columns(rows: list[dict]) -> list[tuple[str, str, int]]:
    """(key, header, digits) per mode; PSNR only when some run has it."""
    cols = [("accuracy", "Acc.", 2), ("completeness", "Comp.", 2), ("overall", "Chamfer", 2)]
    optional = [("overall_dtu_rule", "DTU rule", 2), ("mesh_accuracy", "mesh Acc.", 2),
                ("mesh_completeness", "mesh Comp.", 2), ("mesh_overall", "mesh", 2),
                ("mesh_overall_dtu_rule", "mesh DTU rule", 2), ("psnr", "PSNR", 2),
                ("ssim", "SSIM", 3), ("lpips", "LPIPS", 3), ("psnr_ibr", "PSNR IBR", 2),
                ("ssim_ibr", "SSIM IBR", 3), ("lpips_ibr", "LPIPS IBR", 3)]
    cols += [c for c in optional if any(r.get(c[0]) is not None for r in rows)]
    cols.append(("time_s", "time (s)", 0))
    return cols


def protocol_groups(rows: list[dict]) -> list[tuple[str | None, list[dict]]]:
    """The rows split by the Chamfer protocol they were scored under (``protocol``; see
    `svolsdf.evaluate.run_outputs.PROTOCOLS`), in order of appearance: numbers of two protocols
    measure different things (the DTU protocol, the whole --gt-points cloud, the part of a
    synthetic scene the inputs see) and never share a column or a mean. A row without one (a
    failed run, no ground truth) joins the group of its scene, else the first group."""
    order: list[str | None] = []
    by_scene: dict[str, str] = {}
    for r in rows:
        p = r.get("protocol")
        if p is not None:
            by_scene.setdefault(r["scene"], p)
            if p not in order:
                order.append(p)
    if not order:
        return [(None, list(rows))]
    groups: dict = {p: [] for p in order}
    for r in rows:
        p = r.get("protocol")
        groups[p if p is not None else by_scene.get(r["scene"], order[0])].append(r)
    return list(groups.items())


def _check_one_protocol(rows: list[dict]) -> None:
    protocols = sorted({str(r["protocol"]) for r in rows if r.get("protocol") is not None})
    if len(protocols) > 1:
        which = "; ".join(f"{p}: " + ", ".join(f"{r['scene']} / {r['mode']}" for r in rows
                                               if r.get("protocol") == p) for p in protocols)
        raise InputError(f"benchmark table: runs scored under different Chamfer protocols "
                         f"({which}) cannot share a column or a mean; split the rows with "
                         "protocol_groups")


def _table(rows: list[dict], modes: list[str] | None):
    _check_one_protocol(rows)
    scenes, modes, cell = _grid(rows, modes)
    cols = _columns(rows)
    body = []
    for s in scenes:
        body.append((s, [[cell.get((s, m), {}).get(k) for k, _, _ in cols] for m in modes]))
    means, partial = [], []
    for j in range(len(modes)):
        vals, part = [], []
        for c in range(len(cols)):
            col = [b[1][j][c] for b in body]
            vals.append(_mean(col))
            n = sum(v is not None and math.isfinite(float(v)) for v in col)
            part.append(0 < n < len(col))
        means.append(vals)
        partial.append(part)
    return scenes, modes, cols, body, means, partial


def _mesh_source_notes(rows: list[dict]) -> list[str]:
    """Lines saying which surface the mesh columns hold (``mesh_source`` of each row): one
    line when every run's mesh is the same kind, else every run's kind, so that a column never
    mixes kinds unsaid."""
    kinds = {(r["scene"], r["mode"]): r.get("mesh_source") for r in rows
             if r.get("mesh_overall") is not None}
    if not kinds:
        return []
    distinct = sorted({str(k) for k in kinds.values()})
    if len(distinct) == 1:
        return ["", f"mesh.ply of every run with a mesh column: {distinct[0]}."]
    return ["", "The mesh columns mix surfaces; mesh.ply of each run:", ""] + [
        f"- {s} / {m}: {k}" for (s, m), k in kinds.items()]


def _mesh_sampling_notes(rows: list[dict]) -> list[str]:
    """A line saying how the mesh columns were scored (``mesh_sampled`` of each row): by the
    mesh's surface, or, for rows from metrics of a time when meshes were scored by their
    vertices, a list of those rows, so that the two are never mixed unsaid."""
    scored = [r for r in rows if r.get("mesh_overall") is not None]
    if not scored:
        return []
    old = [r for r in scored if r.get("mesh_sampled") != "surface"]
    if not old:
        return ["", "The mesh columns score mesh.ply by its surface, its triangles sampled at "
                "the protocol's density (DTU 0.2 mm, otherwise 0.1 % of the ground truth's "
                "diagonal), not by its vertices."]
    return ["", "The mesh columns mix scorings: these runs' meshes were scored by their vertices "
            "(metrics written before meshes were scored by their surface), not comparable with "
            "the others:", ""] + [f"- {r['scene']} / {r['mode']}" for r in old]


def benchmark_markdown(rows: list[dict], modes: list[str] | None = None,
                       title: str = "Benchmark", notes: list[str] | None = None) -> str:
    """A Markdown table like the paper's Table 1 from per-run metrics dicts.

    Args:
        rows: one dict per run with ``scene``, ``mode`` and any of `METRIC_KEYS` (None or
            missing: not computed), optionally ``status`` (anything but "ok" is listed below
            the table) and ``protocol`` (how the Chamfer was computed).
        modes: column order (default: modes in order of appearance).
        title: the heading.
        notes: extra lines under the table.

    Returns:
        The Markdown text: a table with one row per scene and a mean row (mean over the scenes
        that have the value; marked * when some do not), per mode the accuracy, completeness and
        overall Chamfer, PSNR when any run has it, and time; the lowest Chamfer of each row in
        bold.
    """
    if not rows:
        raise InputError("benchmark table: no runs to tabulate")
    groups = protocol_groups(rows)
    if len(groups) > 1:  # one table per protocol: never two protocols in one column
        from svolsdf.evaluate.run_outputs import protocol_label

        names = _mode_labels(rows, modes or list(dict.fromkeys(r["mode"] for r in rows)))
        out = [f"# {title}", "", "Methods: " + "; ".join(f"{m} = {n}" for m, n in names.items())
               + ".", "", "The runs were scored under different Chamfer protocols, which "
               "measure different things: one table per protocol, no mean across them.", ""]
        for p, group in groups:
            text = benchmark_markdown(group, modes, title=f"Chamfer protocol: {p}")
            body = text.splitlines()[4:]  # without its title and methods line
            out += [f"## Chamfer protocol: {p} ({protocol_label(p)})", ""] + body + [""]
        if notes:
            out += list(notes)
        return "\n".join(out).rstrip("\n") + "\n"
    scenes, modes, cols, body, means, partial = _table(rows, modes)
    head = ["scene"] + [f"{m} {h}" for m in modes for _, h, _ in cols]
    names = _mode_labels(rows, modes)
    out = [f"# {title}", "",
           "Methods: " + "; ".join(f"{m} = {names[m]}" for m in modes) + ".", "",
           "| " + " | ".join(head) + " |", "|---|" + "---:|" * (len(head) - 1)]
    ci = [k for k, _, _ in cols].index("overall")

    def line(label, per_mode, marks=None):
        best = [v[ci] for v in per_mode if v[ci] is not None and math.isfinite(v[ci])]
        best = min(best) if len(best) > 1 else None
        cells = []
        for j, vals in enumerate(per_mode):
            for c, (_, _, digits) in enumerate(cols):
                t = _fmt(vals[c], digits)
                if marks and marks[j][c] and t != "-":
                    t += "*"
                if c == ci and best is not None and vals[c] == best:
                    t = f"**{t}**"
                cells.append(t)
        return "| " + " | ".join([label] + cells) + " |"

    for s, per_mode in body:
        out.append(line(s, per_mode))
    out.append(line("**mean**", means, partial))
    out.append("")
    protocols = sorted({r.get("protocol") for r in rows if r.get("protocol")})
    out.append("Chamfer: accuracy (prediction -> ground truth), completeness (ground truth -> "
               "prediction) and their mean, of the fused point cloud, in the scene's world units "
               f"(DTU: mm); protocol: {', '.join(protocols) if protocols else 'none'}. "
               + ("'DTU rule': distances beyond the clipping distance left out. "
                  if "overall_dtu_rule" in [k for k, _, _ in cols] else "")
               + ("'mesh': the same of mesh.ply's surface. "
                  if "mesh_overall" in [k for k, _, _ in cols] else "")
               + ("PSNR / SSIM / LPIPS on held-out views, by volume rendering and by IBR. "
                  if "psnr" in [k for k, _, _ in cols] else "")
               + "Time: the pipeline's stage times. "
               "'-': not computed; '*': mean over fewer scenes than the table has.")
    out += _mesh_source_notes(rows)
    out += _mesh_sampling_notes(rows)
    failed = [r for r in rows if r.get("status", "ok") != "ok"]
    if failed:
        out += ["", "Runs without results:", ""]
        out += [f"- {r['scene']} / {r['mode']}: {r['status']}" for r in failed]
    if notes:
        out += [""] + list(notes)
    return "\n".join(out) + "\n"


def benchmark_csv(rows: list[dict], modes: list[str] | None = None) -> str:
    """The same table as `benchmark_markdown` as CSV: a ``scene`` column, then
    ``<mode>_<metric>`` columns, one line per scene and a last line ``mean``; empty cells for
    values not computed; full precision."""
    if not rows:
        raise InputError("benchmark table: no runs to tabulate")
    groups = protocol_groups(rows)
    if len(groups) > 1:  # a leading protocol column, and one mean per protocol
        modes = modes or list(dict.fromkeys(r["mode"] for r in rows))
        tables = [list(csv.DictReader(io.StringIO(benchmark_csv(g, modes)))) for _, g in groups]
        head = list(dict.fromkeys(k for t in tables for line in t for k in line))
        buf = io.StringIO()
        w = csv.writer(buf, lineterminator="\n")
        w.writerow(["protocol"] + head)
        for (p, _), t in zip(groups, tables, strict=True):
            for line in t:
                w.writerow([p] + [line.get(k, "") for k in head])
        return buf.getvalue()
    scenes, modes, cols, body, means, _ = _table(rows, modes)
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(["scene"] + [f"{m}_{k}" for m in modes for k, _, _ in cols])
    for label, per_mode in [*body, ("mean", means)]:
        w.writerow([label] + ["" if v is None or not math.isfinite(v) else repr(float(v))
                              for vals in per_mode for v in vals])
    return buf.getvalue()


def benchmark_plot(rows: list[dict], path: Path, modes: list[str] | None = None) -> Path:
    """A bar chart of the table: overall Chamfer per scene and mode (and PSNR when any run has
    it), the mean last; written to ``path`` (PNG).

    Args:
        rows: as `benchmark_markdown`'s.
        path: the image file to write.
        modes: bar order (default: modes in order of appearance).

    Returns:
        ``path``.
    """
    if not rows:
        raise InputError("benchmark plot: no runs to plot")
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    groups = protocol_groups(rows)
    if len(groups) > 1:  # one chart per protocol, beside each other in name
        for p, group in groups:
            benchmark_plot(group, Path(path).with_name(f"{Path(path).stem}_{p}.png"), modes)
        return Path(path).with_name(f"{Path(path).stem}_{groups[0][0]}.png")
    scenes, modes, cols, body, means, _ = _table(rows, modes)
    names = _mode_labels(rows, modes)
    keys = [k for k, _, _ in cols]
    panels = [("overall", "Chamfer (lower is better)")]
    if "psnr" in keys:
        panels.append(("psnr", "PSNR (dB, higher is better)"))
    labels = scenes + ["mean"]
    per = [b[1] for b in body] + [means]
    fig, axes = plt.subplots(len(panels), 1, squeeze=False,
                             figsize=(max(4.0, 0.9 * len(labels) * max(1, len(modes)) + 1.5),
                                      2.8 * len(panels)))
    width = 0.8 / max(1, len(modes))
    for ax, (key, title) in zip(axes[:, 0], panels, strict=True):
        c = keys.index(key)
        for j, m in enumerate(modes):
            vals = [v[j][c] for v in per]
            # not computed: no bar (NaN), not a zero that would read as a perfect score
            ys = [float(v) if v is not None else math.nan for v in vals]
            xs = [i + (j - (len(modes) - 1) / 2) * width for i in range(len(labels))]
            ax.bar(xs, ys, width, label=names[m])
        ax.set_xticks(range(len(labels)), labels, rotation=30 if len(labels) > 6 else 0,
                      ha="right" if len(labels) > 6 else "center")
        ax.set_title(title, fontsize=10)
        ax.grid(axis="y", alpha=0.3)
    axes[0, 0].legend(fontsize=8)
    fig.tight_layout()
    from svolsdf.io.images import save_figure

    return save_figure(fig, path)
