"""The reconstruction's stages, one declared `Stage` per file, in the order the runner
(`svolsdf.pipeline.runner.Pipeline`) drives them (docs/architecture.md "Data flow"):

1. ``mvs1`` (`mvs1.py`): stage-1 probability volumes of the input views.
2. ``field`` (`field.py`): the S-VolSDF optimization.
3. ``guide`` (`guide.py`): the field's rendered z-depth of the input views (docs/method.md 6.1).
4. ``mvs23`` (`mvs23.py`): MVS stages 2 and 3 centred on that depth.
5. ``unguided`` (`unguided.py`): stages 2 and 3 centred on the stage-1 depth (``fusion.unguided``).
6. ``fusion`` (`fusion.py`): geometric-consistency filtering and fusion (docs/method.md 6.3).
7. ``mesh`` (`mesh.py`): the mesh the config asks for.
"""

from svolsdf.pipeline.stages.base import SCENE_OPTIONS, Stage, StageResult
from svolsdf.pipeline.stages.field import Field
from svolsdf.pipeline.stages.fusion import Fusion
from svolsdf.pipeline.stages.guide import Guide
from svolsdf.pipeline.stages.mesh import Mesh
from svolsdf.pipeline.stages.mvs1 import MVS1
from svolsdf.pipeline.stages.mvs23 import MVS23
from svolsdf.pipeline.stages.unguided import Unguided

__all__ = ["PIPELINE_STAGES", "SCENE_OPTIONS", "Stage", "StageResult", "stage"]

PIPELINE_STAGES: tuple[Stage, ...] = (MVS1(), Field(), Guide(), MVS23(), Unguided(), Fusion(),
                                      Mesh())
"""Every stage, in the order they run (their names are `svolsdf.pipeline.keys.STAGES`)."""


def stage(name: str) -> Stage:
    """The stage called ``name``."""
    for s in PIPELINE_STAGES:
        if s.name == name:
            return s
    raise KeyError(name)
