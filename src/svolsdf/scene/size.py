"""Image sizes: the one ``WxH`` parser of every command and the one working-size rule.

The working size is the resolution at which the field is optimized and the MVS cascade's scale
is counted from. Every command that loads a scene (`svolsdf reconstruct`, `svolsdf mvs`) picks it
with `working_size`, so the same scene runs at the same size in both.
"""

from __future__ import annotations

from svolsdf.errors import InputError

__all__ = ["DEFAULT_MAX_WIDTH", "parse_size", "working_size"]

#: default working width: DTU's 1600x1200 photos run at 768x576
DEFAULT_MAX_WIDTH = 768


def parse_size(text: str, option: str = "--size") -> tuple[int, int]:
    """``"768x576"`` (or ``768*576``) -> (768, 576).

    Raises:
        InputError: naming ``option``, when the text is not WIDTHxHEIGHT or a side is outside
            8..16384.
    """
    parts = str(text).lower().replace("*", "x").split("x")
    try:
        if len(parts) != 2:
            raise ValueError
        w, h = int(parts[0]), int(parts[1])
    except ValueError:
        raise InputError(
            f"{option} must look like WIDTHxHEIGHT (e.g. 768x576), got {text!r}"
        ) from None
    if w < 8 or h < 8 or w > 16384 or h > 16384:
        raise InputError(f"{option} {text!r}: width and height must be within 8..16384")
    return w, h


def working_size(width: int, height: int, image_size: tuple[int, int] | list[int] | None = None,
                 max_width: int = DEFAULT_MAX_WIDTH) -> tuple[int, int]:
    """(W, H) to work at for images of ``width`` x ``height``.

    ``image_size`` [W, H] when given (``scene.image_size``, as the user asked, unrounded); else
    at most ``max_width`` wide, never upsampled, the aspect kept, both sides multiples of 8
    (rounded down when not shrinking, to the nearest when shrinking), so that the cascade's
    stages halve the size exactly.
    """
    if image_size is not None:
        return int(image_size[0]), int(image_size[1])
    if width <= max_width:
        return max(8, width - width % 8), max(8, height - height % 8)
    s = max_width / width
    return max_width, max(8, int(round(height * s / 8)) * 8)
