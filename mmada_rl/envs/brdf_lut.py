"""SAPIEN's BRDF look-up table, computed once per machine instead of once per rendering process.

SAPIEN's renderer shades with a split-sum BRDF look-up table: a 512×512 texture of
two half floats, the GGX specular integral's scale and bias for each roughness and
view angle. It computes the table when a process renders for the first time, with a
compute shader (``svulkan2::shader::generateBRDFLUT``, from ``brdf_lut.comp``), and
keeps it for the life of that process only. On a CPU Vulkan device (lavapipe) that
shader takes ~6 s of both cores, and every process that renders pays it again: each
recipe run, ``ParallelEnv`` worker, collection worker and collector process
(``benchmarks/first_frame.py``).

The renderer uses a texture named ``BRDFLUT`` from the camera instead, when the
camera has one (SAPIEN's ``RenderCameraComponent.set_texture``). This module computes
the same table with numpy, the same integral with the same 1024 Hammersley samples
in single precision, caches it on disk (``~/.cache/mmada_rl``, or under
``$XDG_CACHE_HOME``), and gives it to every camera that ManiSkill adds to a scene
(:func:`install`, which :func:`~mmada_rl.envs.make_gym_env` calls). The frames
rendered with it are the frames SAPIEN renders with its own table
(``tests/test_envs.py`` compares them).

``MMADA_RL_BRDF_LUT=sapien`` in the environment leaves SAPIEN to compute its own
(to compare: ``benchmarks/first_frame.py``).
"""
from __future__ import annotations

import functools
import os
import tempfile
from pathlib import Path

import numpy as np

__all__ = ["LUT_VARIABLE", "brdf_lut", "cache_path", "compute_brdf_lut", "install", "installed", "lut_source", "lut_texture"]

LUT_VARIABLE = "MMADA_RL_BRDF_LUT"
LUT_SOURCES = ("cached", "sapien")
SIZE = 512  # svulkan2 always asks for 512 (resource/manager.cpp)
SAMPLES = 1024  # brdf_lut.comp's sample count
TEXTURE_NAME = "BRDFLUT"  # the name svulkan2 looks for among a camera's textures
_VERSION = 1  # bump when the computation changes, so old cache files are not read


def compute_brdf_lut(size: int = SIZE, samples: int = SAMPLES) -> np.ndarray:
    """The split-sum GGX look-up table as ``brdf_lut.comp`` computes it, ``(size, size, 2)`` float16.

    Texel ``[y, x]`` holds the integral's scale and bias for roughness ``(x + .5) / size`` and
    ``dot(N, V) = (y + .5) / size``, as ``samples`` importance-sampled GGX half vectors at Hammersley
    points estimate them, in float32 (the shader's precision), stored as the shader's half floats.

    Examples:
        >>> lut = compute_brdf_lut(8, 64)
        >>> lut.shape, lut.dtype
        ((8, 8, 2), dtype('float16'))
        >>> round(float(lut[-1, 0].sum()), 2)  # smooth, seen head-on: scale + bias = 1, all the light reflected
        1.0
    """
    if size < 1 or samples < 1:
        raise ValueError(f"size and samples must be positive, got size={size}, samples={samples}")
    f = np.float32
    index = np.arange(samples, dtype=np.uint32)
    phi = f(2 * np.pi) * (index.astype(f) / f(samples))
    xi = _radical_inverse(index)
    cos_nv = ((np.arange(size, dtype=f) + f(0.5)) / f(size))[:, None]  # one row per view angle
    sin_nv = np.sqrt(f(1) - cos_nv * cos_nv)
    lut = np.empty((size, size, 2), dtype=np.float16)
    for x in range(size):
        roughness = f((x + 0.5) / size)
        a = roughness * roughness
        cos_h = np.sqrt((f(1) - xi) / (f(1) + (a * a - f(1)) * xi))
        sin_h = np.sqrt(f(1) - cos_h * cos_h)
        # the half vector in world space: the shader's tangent frame for N = +z maps (x, y, z) to (y, -x, z)
        h_x, h_z = sin_h * np.sin(phi), cos_h
        v_dot_h = sin_nv * h_x + cos_nv * h_z
        n_dot_l = f(2) * v_dot_h * h_z - cos_nv
        k = (roughness / f(2)) ** 2
        lit = n_dot_l > 0
        n_dot_l = np.maximum(n_dot_l, f(0))
        v_dot_h = np.maximum(v_dot_h, f(0))
        g_vis = n_dot_l / ((cos_nv * (f(1) - k) + k) * (n_dot_l * (f(1) - k) + k)) * v_dot_h / np.maximum(h_z, f(0))
        fresnel = (f(1) - v_dot_h) ** 5
        lut[:, x, 0] = np.where(lit, (f(1) - fresnel) * g_vis, f(0)).sum(1, dtype=f) / f(samples)
        lut[:, x, 1] = np.where(lit, fresnel * g_vis, f(0)).sum(1, dtype=f) / f(samples)
    return lut


def _radical_inverse(index: np.ndarray) -> np.ndarray:
    """Van der Corput's radical inverse in base 2 of each uint32 (the bits reversed, over 2**32)."""
    bits = index.astype(np.uint32)
    bits = (bits << np.uint32(16)) | (bits >> np.uint32(16))
    for shift, mask in ((1, 0x55555555), (2, 0x33333333), (4, 0x0F0F0F0F), (8, 0x00FF00FF)):
        low, high = np.uint32(mask), np.uint32(~mask & 0xFFFFFFFF)
        bits = ((bits & low) << np.uint32(shift)) | ((bits & high) >> np.uint32(shift))
    return bits.astype(np.float32) * np.float32(2.3283064365386963e-10)


def cache_path(size: int = SIZE, samples: int = SAMPLES) -> Path:
    """Where :func:`brdf_lut` keeps the table: ``$XDG_CACHE_HOME/mmada_rl`` (default ``~/.cache/mmada_rl``)."""
    root = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache")
    return root / "mmada_rl" / f"brdf_lut_v{_VERSION}_{size}x{size}_{samples}.npy"


@functools.lru_cache(maxsize=None)
def brdf_lut(size: int = SIZE, samples: int = SAMPLES) -> np.ndarray:
    """:func:`compute_brdf_lut`'s table, read from :func:`cache_path` or computed (~5.5 s) and written there.

    The file is written whole under another name and then renamed, so processes that start together read
    either nothing or the whole table. A file that is not a table of the right shape is computed again; a
    cache directory that cannot be written only costs the computation in each process.
    """
    path = cache_path(size, samples)
    try:
        lut = np.load(path, allow_pickle=False)
        if lut.shape == (size, size, 2) and lut.dtype == np.float16:
            return lut
    except (OSError, ValueError):
        pass
    lut = compute_brdf_lut(size, samples)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        with tempfile.NamedTemporaryFile(dir=path.parent, prefix=path.stem, suffix=".tmp", delete=False) as tmp:
            np.save(tmp, lut, allow_pickle=False)
        os.chmod(tmp.name, 0o644)  # readable by all, like any cache file (the temporary file was 0600)
        os.replace(tmp.name, path)
    except OSError:
        pass
    return lut


def lut_source() -> str:
    """``"cached"`` (the default: :func:`install` gives cameras the table) or ``"sapien"``, from :data:`LUT_VARIABLE`.

    Raises:
        ValueError: :data:`LUT_VARIABLE` names something else.
    """
    source = os.environ.get(LUT_VARIABLE, "cached")
    if source not in LUT_SOURCES:
        raise ValueError(f"{LUT_VARIABLE}={source!r}: expected one of {', '.join(LUT_SOURCES)}")
    return source


def lut_texture(table: np.ndarray):
    """``table`` (``(size, size, 2)`` float16) as the SAPIEN texture a camera takes for ``BRDFLUT``: two half floats
    per texel, as svulkan2's own, sampled linearly and clamped at the edges."""
    import sapien

    return sapien.render.RenderTexture(table, 2, "R16G16Sfloat", filter_mode="linear", address_mode="edge")


@functools.lru_cache(maxsize=None)
def _texture():
    """:func:`brdf_lut`'s table as a texture, one per process (made at the first camera, the render device up)."""
    return lut_texture(brdf_lut())


def installed() -> bool:
    """Whether ManiSkill's scenes give their new cameras the table (:func:`install` has run in this process)."""
    from mani_skill.envs.scene import ManiSkillScene

    return getattr(ManiSkillScene.add_camera, "_gives_brdf_lut", False)


def install() -> bool:
    """Make every camera ManiSkill adds to a scene from now on, in this process, use :func:`brdf_lut`'s table.

    Wraps ``ManiSkillScene.add_camera`` (sensors, the render camera for videos, both): each of the new camera's
    SAPIEN components gets the texture before it renders anything. Idempotent. Returns whether the table is
    installed: ``False`` when :data:`LUT_VARIABLE` is ``sapien``.

    Raises:
        ValueError: :data:`LUT_VARIABLE` names something else.
    """
    if lut_source() == "sapien":
        return False
    from mani_skill.envs.scene import ManiSkillScene

    if installed():
        return True
    add_camera = ManiSkillScene.add_camera

    @functools.wraps(add_camera)
    def add_camera_with_brdf_lut(self, *args, **kwargs):
        camera = add_camera(self, *args, **kwargs)
        for component in camera._render_cameras:
            component.set_texture(TEXTURE_NAME, _texture())
        return camera

    add_camera_with_brdf_lut._gives_brdf_lut = True
    ManiSkillScene.add_camera = add_camera_with_brdf_lut
    return True
