"""Linear (HDR) variants of SAPIEN's rasterisation shaders, derived at run time.

SAPIEN's ``minimal`` and ``default`` shaders end by display-encoding the colour and clipping it:
``clamp(pow(color, 1/2.2), 0, 1)``. A white surface near the vehicle's lamp (radiance 14 at
0.5 m under the default lamp) then comes out as 1.0 before the water and the sensor are applied,
where no camera would clip: a real camera sees the attenuated light through the water and
clips at its sensor, after its exposure. So the renderer uses variants of those shaders whose
``Color`` picture is the linear radiance, unclipped (``sim.water`` applies the water, the
exposure and the sensor's clipping).

The variants are not shipped: they are derived from the installed SAPIEN's own shader files
(a few lines of each replaced, :data:`EDITS`) into the toolkit's cache
(``<cache>/shaders-<sapien version>-<hash>/``) the first time a camera needs them. An edit whose
line is missing (a SAPIEN whose shaders changed) stops with one line naming the file.

The ``minimal`` variant also skips two passes of work whose result is exactly nothing in the
toolkit's scenes (:data:`FAST_EDITS`, measured equal picture for picture in
``tests/test_shaders.py``): the image-based lighting (the scenes set no environment map, so its
samples are black: under water there is no sky to reflect) and, in the composite pass, the
background lookup for pixels an opaque surface covers (its weight there is 0). And it writes
no position picture: the composite pass puts each pixel's depth, from the depth buffer, into
the colour's alpha channel (:data:`DEPTH_IN_ALPHA`), so a frame is one picture read back, its
depth in float instead of whole millimetres. On the CPU (lavapipe), where the fragment shading
is most of a frame's time, the three take about half off a 480 px render.
"""

from __future__ import annotations

import functools
import hashlib
import shutil
from pathlib import Path

import sapien

from uwdock.dockcore.errors import DockError
from uwdock.sim.cache import build_once, cache_root

__all__ = ["DEPTH_IN_ALPHA", "EDITS", "FAST_EDITS", "hdr_shader_dir", "sapien_shader_root"]

#: (shader folder, file) -> (SAPIEN's line, its linear replacement). The background (the
#: environment map) is linearised too, so a picture is linear everywhere.
EDITS: dict[tuple[str, str], tuple[tuple[str, str], ...]] = {
    ("minimal", "gbuffer.frag"): (
        (
            "outColorRaw = vec4(clamp(pow(color, vec3(1/2.2)), vec3(0), vec3(1)), albedo.a);",
            "outColorRaw = vec4(max(color, vec3(0)), albedo.a);",
        ),
    ),
    ("minimal", "composite0.frag"): (
        (
            "vec3 bg = pow(getBackgroundColor((cameraBuffer.viewMatrixInverse * csPosition).xyz),"
            " vec3(1/2.2));",
            "vec3 bg = getBackgroundColor((cameraBuffer.viewMatrixInverse * csPosition).xyz);",
        ),
    ),
    ("default", "composite0.frag"): (
        (
            "outColor.rgb = pow(outColor.rgb * exposure, vec3(1/2.2));",
            "outColor.rgb = outColor.rgb * exposure;",
        ),
        (
            "outColor = clamp(outColor, vec4(0), vec4(1));",
            "outColor = max(outColor, vec4(0));",
        ),
    ),
}

#: Edits of the ``minimal`` variant that skip work adding exactly nothing in the toolkit's
#: scenes (module docstring), applied after :data:`EDITS`; its ``Color`` picture then carries
#: the depth in its alpha channel (:data:`DEPTH_IN_ALPHA`).
FAST_EDITS: dict[tuple[str, str], tuple[tuple[str, str], ...]] = {
    ("minimal", "gbuffer.frag"): (
        (
            "  color += diffuseIBL(diffuseAlbedo, wnormal);\n"
            "  color += specularIBL(fresnel, roughness,\n"
            "                       wnormal,\n"
            "                       mat3(cameraBuffer.viewMatrixInverse) * camDir);\n",
            "  // no image-based lighting: no environment map (uwdock.sim.shaders)\n",
        ),
        ("layout(location = 1) out ivec4 outPositionSegmentation;\n", ""),
        ("  outPositionSegmentation = ivec4(ivec3(inPosition * 1000), inSegmentation[1]);\n", ""),
    ),
    ("minimal", "composite0.frag"): (
        (
            "  float depth = texture(samplerGbufferDepth, inUV).x;\n"
            "  vec4 csPosition = cameraBuffer.projectionMatrixInverse * (vec4(inUV * 2 - 1, depth,"
            " 1));\n"
            "  csPosition /= csPosition.w;\n"
            "  vec3 bg = getBackgroundColor((cameraBuffer.viewMatrixInverse * csPosition).xyz);\n"
            "\n"
            "  outColor.rgb = mix(bg, color.rgb, color.a);\n"
            "  outColor.a = color.a;\n",
            "  float depth = texture(samplerGbufferDepth, inUV).x;\n"
            "  vec4 csPosition = cameraBuffer.projectionMatrixInverse * (vec4(inUV * 2 - 1, depth,"
            " 1));\n"
            "  csPosition /= csPosition.w;\n"
            "  outColor.rgb = color.rgb;\n"
            "  if (color.a < 1.0) {  // the background shows: look it up (uwdock.sim.shaders)\n"
            "    vec3 bg = getBackgroundColor((cameraBuffer.viewMatrixInverse * csPosition).xyz);\n"
            "    outColor.rgb = mix(bg, color.rgb, color.a);\n"
            "  }\n"
            "  // alpha: the depth (m, > 0) where a surface was hit, 0 elsewhere\n"
            "  outColor.a = depth < 1.0 ? -csPosition.z : 0.0;\n",
        ),
    ),
}

#: The shaders whose fast variant writes the depth (z in the camera, m; 0 where nothing was hit)
#: into the ``Color`` picture's alpha channel instead of a second picture.
DEPTH_IN_ALPHA = frozenset({"minimal"})

#: Folders beside the shader folders that their ``#include "../common/..."`` lines read.
_SHARED = ("common",)
_DONE = "DERIVED"


def sapien_shader_root() -> Path:
    """The installed SAPIEN's shader folder (``.../sapien/vulkan_shader``)."""
    return Path(sapien.__file__).parent / "vulkan_shader"


def _patched(root: Path, shader: str, fast: bool) -> dict[str, str]:
    """File name -> text of the linear variant of SAPIEN's ``shader`` folder (with
    :data:`FAST_EDITS` when ``fast``)."""
    tables = (EDITS, FAST_EDITS) if fast else (EDITS,)
    out = {}
    for path in sorted((root / shader).iterdir()):
        if not path.is_file():
            continue
        text = path.read_text(encoding="utf-8")
        edits = [e for table in tables for e in table.get((shader, path.name), ())]
        for old, new in edits:
            if text.count(old) != 1:
                raise DockError(
                    f"cannot derive the linear {shader!r} shader: {path} does not hold the line "
                    f"{old!r} once (SAPIEN {sapien.__version__}'s shaders differ from what "
                    "uwdock.sim.shaders expects)"
                )
            text = text.replace(old, new)
        out[path.name] = text
    missing = {name for table in tables for (sh, name) in table if sh == shader} - set(out)
    if missing:
        raise DockError(
            f"cannot derive the linear {shader!r} shader: {root / shader} lacks {missing}"
        )
    return out


@functools.lru_cache(maxsize=8)
def hdr_shader_dir(shader: str, fast: bool = True) -> str:
    """The folder of the linear (HDR) variant of SAPIEN's ``minimal`` or ``default`` shader,
    derived into the cache on first use (see the module docstring). ``fast=False`` leaves out
    :data:`FAST_EDITS` (the reference they are tested against).

    Raises:
        ValueError: a shader without a linear variant.
        DockError: SAPIEN's shader files are not what :data:`EDITS` expects, or the cache cannot
            be written.
    """
    if shader not in {sh for sh, _ in EDITS}:
        raise ValueError(f"shader: no linear variant of {shader!r}; known: minimal, default")
    root = sapien_shader_root()
    files = _patched(root, shader, fast)
    h = hashlib.sha1()
    for name in sorted(files):
        h.update(name.encode() + b"\0" + files[name].encode() + b"\0")
    for folder in _SHARED:
        for path in sorted((root / folder).rglob("*")):
            if path.is_file():
                h.update(str(path.relative_to(root)).encode() + b"\0" + path.read_bytes())
    final = cache_root() / f"shaders-{sapien.__version__}-{shader}-{h.hexdigest()[:12]}"

    def make(tmp: Path) -> None:
        for folder in _SHARED:
            shutil.copytree(root / folder, tmp / folder)
        (tmp / shader).mkdir()
        for name, text in files.items():
            (tmp / shader / name).write_text(text, encoding="utf-8")
        (tmp / _DONE).write_text(f"derived from {root} (SAPIEN {sapien.__version__})\n")

    try:
        build_once(final, _DONE, make)
    except OSError as exc:
        raise DockError(
            f"cannot write the linear shaders into the cache {final.parent}: {exc}"
        ) from None
    return str(final / shader)
