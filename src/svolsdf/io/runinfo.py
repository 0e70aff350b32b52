"""Facts about a finished run read from its OUT/timing.json, for every command that reports
on a run (evaluate, report, benchmark tables)."""

from __future__ import annotations

__all__ = ["mesh_source"]


def mesh_source(timing: dict | None) -> str | None:
    """Which surface OUT/mesh.ply is: "field", "poisson", "tsdf", or "field (poisson failed:
    REASON)" when the method asked for gave no mesh and the field's zero level replaced it;
    None when the run made no mesh (or its timing.json does not say).

    Args:
        timing: the parsed OUT/timing.json ({stage: {...}}), or None.
    """
    m = (timing or {}).get("mesh")
    if not isinstance(m, dict):
        return None
    if m.get("mesh_source"):
        return str(m["mesh_source"])
    # run folders written before mesh_source existed
    if m.get("poisson_failed"):
        return f"field (poisson failed: {m['poisson_failed']})"
    return str(m.get("method") or "field")
