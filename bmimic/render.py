"""Offscreen rendering of a tracking rollout: the simulated robot plus a translucent reference ghost.

MuJoCo picks its OpenGL backend from MUJOCO_GL when `mujoco` is first imported, so a tool that
renders calls `select_gl_backend()` before importing anything that imports mujoco. Unset, it tries
EGL (GPU or Mesa) and then OSMesa (software) in a throw-away subprocess and keeps the first one that
can create a context; set MUJOCO_GL yourself to skip the probe.

Videos are MP4 (H.264) when imageio and imageio-ffmpeg are installed, otherwise GIF through Pillow.
"""

from __future__ import annotations

import logging
import os
import subprocess
import sys
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from bmimic import BmimicError

log = logging.getLogger(__name__)
# PyOpenGL logs "No OpenGL_accelerate module loaded" at INFO when its optional C speed-up is absent: not
# a problem of the render (bmimic draws a few frames per step), so not a line on the console.
logging.getLogger("OpenGL.acceleratesupport").setLevel(logging.WARNING)

GL_BACKENDS = ("egl", "osmesa")
"""Headless backends tried, in order, when MUJOCO_GL is unset."""
_USABLE_GL = ("egl", "osmesa", "glfw", "glx", "cgl", "wgl", "enable", "enabled", "on", "true", "1")
GHOST_RGBA = (0.35, 0.75, 1.0, 0.35)
"""Colour of the reference ghost (translucent light blue)."""

_PROBE = (
    "import mujoco\n"
    "m = mujoco.MjModel.from_xml_string('<mujoco><worldbody><geom size=\"0.1\"/></worldbody></mujoco>')\n"
    "r = mujoco.Renderer(m, 8, 8)\n"
    "r.render()\n"
    "r.close()\n"
)


class RenderError(BmimicError):
    """Offscreen rendering is not possible here (no GL backend, bad size, no video writer)."""


# --------------------------------------------------------------------------------------------- GL backend
def probe_gl_backend(backend: str, timeout_s: float = 60.0) -> str | None:
    """None when MuJoCo can render offscreen with `backend` (checked in a subprocess), else why not."""
    env = {**os.environ, "MUJOCO_GL": backend}
    env.pop("PYOPENGL_PLATFORM", None)  # mujoco sets it to match the backend
    try:
        out = subprocess.run([sys.executable, "-c", _PROBE], env=env, capture_output=True, text=True,
                             timeout=timeout_s)
    except (OSError, subprocess.SubprocessError) as e:
        return f"{type(e).__name__}: {e}"
    if out.returncode == 0:
        return None
    lines = [x for x in out.stderr.strip().splitlines() if x.strip()]
    return lines[-1] if lines else f"exit status {out.returncode}"


def select_gl_backend(candidates: Sequence[str] = GL_BACKENDS) -> str:
    """MUJOCO_GL if set; else the first of `candidates` that works, exported to MUJOCO_GL.

    Must run before mujoco is imported (the backend is fixed at import). Raises RenderError naming
    what each backend said when none works.
    """
    current = os.environ.get("MUJOCO_GL", "").strip()
    if current:
        if current.lower() not in _USABLE_GL:  # mujoco would raise at import, or render nothing
            raise RenderError(f"MUJOCO_GL={current}: offscreen rendering needs egl or osmesa (or glfw with a display)")
        return current
    if "mujoco" in sys.modules:  # too late to choose: mujoco has already bound its default (GLFW)
        log.warning("mujoco was imported before a GL backend was chosen; set MUJOCO_GL=egl or osmesa")
        return ""
    reasons = []
    for backend in candidates:
        why = probe_gl_backend(backend)
        if why is None:
            os.environ["MUJOCO_GL"] = backend
            log.info("offscreen rendering with MUJOCO_GL=%s", backend)
            return backend
        reasons.append(f"{backend}: {why}")
    raise RenderError("no OpenGL backend for offscreen rendering (" + "; ".join(reasons) + "); install EGL "
                      "(libegl1) or OSMesa (libosmesa6) drivers, or set MUJOCO_GL")


# --------------------------------------------------------------------------------------------- scene
class TrackingRenderer:
    """Renders world 0 of a batched simulation with the reference pose drawn as a ghost.

    Each frame copies the device state of one world into a host `MjData` (`mujoco_warp.get_data_into`),
    builds the scene from it through `camera` (the robot's `tracking` camera by default), then adds a
    second copy of the robot's dynamic geoms posed at the reference `qpos`, recoloured translucent.
    """

    def __init__(self, mjm, width: int = 640, height: int = 480, camera: str = "tracking",
                 ghost_rgba: Sequence[float] = GHOST_RGBA, msaa: int | None = None) -> None:
        import mujoco

        if width < 16 or height < 16:
            raise RenderError(f"video size {width}x{height}: width and height must be at least 16 pixels")
        self.mjm = mjm
        self.width, self.height = width, height
        # The offscreen framebuffer must be at least the image size; it does not affect physics.
        mjm.vis.global_.offwidth = max(int(mjm.vis.global_.offwidth), width)
        mjm.vis.global_.offheight = max(int(mjm.vis.global_.offheight), height)
        self.renderer = self._make_renderer()
        self.gl_renderer = self._gl_renderer_name()
        if msaa is None:
            # Multisampling costs a software rasteriser ~5x per frame (llvmpipe); GPUs do it for free.
            msaa = 0 if _is_software(self.gl_renderer) else int(mjm.vis.quality.offsamples)
        if msaa != int(mjm.vis.quality.offsamples):
            mjm.vis.quality.offsamples = msaa  # read when the framebuffer is made: make it again
            self.renderer.close()
            self.renderer = self._make_renderer()
        log.info("renderer: %s, %d MSAA samples", self.gl_renderer or "unknown OpenGL", msaa)
        self.data = mujoco.MjData(mjm)
        self.ghost = mujoco.MjData(mjm)
        self.option = mujoco.MjvOption()  # default groups: 0-2 shown, collision geoms (group 3) hidden
        self.perturb = mujoco.MjvPerturb()
        self.ghost_rgba = np.asarray(ghost_rgba, dtype=np.float32)
        self.camera = self._camera(camera)

    def _make_renderer(self):
        import mujoco

        try:
            return mujoco.Renderer(self.mjm, height=self.height, width=self.width)
        except Exception as e:  # each backend fails differently (ImportError, FatalError, AttributeError...)
            backend = os.environ.get("MUJOCO_GL", "") or "default (glfw)"
            text = str(e).strip().splitlines()
            raise RenderError(f"cannot create an offscreen renderer with MUJOCO_GL={backend}: "
                              f"{text[0] if text else type(e).__name__}; try MUJOCO_GL=egl or osmesa") from None

    def _gl_renderer_name(self) -> str:
        """GL_RENDERER of the context ('' when it cannot be asked)."""
        try:
            from OpenGL import GL

            self.renderer._gl_context.make_current()
            name = GL.glGetString(GL.GL_RENDERER)
            return name.decode() if isinstance(name, bytes) else str(name or "")
        except Exception:  # only a performance hint; never fail over it
            return ""

    def _camera(self, name: str):
        import mujoco

        if mujoco.mj_name2id(self.mjm, mujoco.mjtObj.mjOBJ_CAMERA, name) >= 0:
            return name
        # A model without the named camera: a free camera tracking the robot's root body.
        cam = mujoco.MjvCamera()
        cam.type = mujoco.mjtCamera.mjCAMERA_TRACKING
        cam.trackbodyid = 1
        cam.distance, cam.elevation, cam.azimuth = 3.0, -15.0, 135.0
        return cam

    def render(self, sim_data, ref_qpos: np.ndarray | None, world: int = 0) -> np.ndarray:
        """[H, W, 3] uint8 image of `world` of a mujoco_warp Data, with the ghost at `ref_qpos`."""
        import mujoco_warp as mjw

        mjw.get_data_into(self.data, self.mjm, sim_data, world_id=world)
        self.renderer.update_scene(self.data, camera=self.camera, scene_option=self.option)
        if ref_qpos is not None:
            self.add_ghost(np.asarray(ref_qpos, dtype=np.float64))
        return self.renderer.render()

    def add_ghost(self, qpos: np.ndarray) -> None:
        """Add the pose `qpos` to the scene being rendered as a translucent ghost (the reference)."""
        import mujoco

        self.ghost.qpos[:] = qpos
        mujoco.mj_kinematics(self.mjm, self.ghost)
        scene = self.renderer.scene
        first = scene.ngeom
        # Dynamic geoms only: the floor and other world-body geoms must not be drawn twice.
        mujoco.mjv_addGeoms(self.mjm, self.ghost, self.option, self.perturb, mujoco.mjtCatBit.mjCAT_DYNAMIC, scene)
        for i in range(first, scene.ngeom):
            scene.geoms[i].rgba[:] = self.ghost_rgba

    def close(self) -> None:
        self.renderer.close()


def _is_software(gl_renderer: str) -> bool:
    name = gl_renderer.lower()
    return any(k in name for k in ("llvmpipe", "softpipe", "swrast", "software"))


def annotate(image: np.ndarray, lines: Sequence[str], alert: bool = False) -> np.ndarray:
    """Burn a few lines of text into the top-left corner (red when `alert`)."""
    from PIL import Image, ImageDraw, ImageFont

    img = Image.fromarray(image)
    draw = ImageDraw.Draw(img)
    size = max(12, image.shape[0] // 30)
    try:
        font = ImageFont.load_default(size=size)
    except TypeError:  # Pillow < 10.1 has one fixed-size bitmap font
        font = ImageFont.load_default()
    colour = (255, 80, 80) if alert else (255, 255, 255)
    y = 6
    for text in lines:
        draw.text((9, y + 1), text, fill=(0, 0, 0), font=font)
        draw.text((8, y), text, fill=colour, font=font)
        y += int(size * 1.3)
    return np.asarray(img)


# --------------------------------------------------------------------------------------------- video
def mp4_available() -> bool:
    """imageio with its ffmpeg plugin is installed."""
    from bmimic.cli.extras import missing_packages

    return not missing_packages("video")


def video_path(path: Path) -> Path:
    """The path actually written: .mp4 becomes .gif when no MP4 writer is installed."""
    suffix = path.suffix.lower()
    if suffix not in (".mp4", ".gif"):
        raise RenderError(f"--out {path}: the video must end in .mp4 or .gif")
    if suffix == ".mp4" and not mp4_available():
        from bmimic.cli.extras import install_command, missing_packages

        log.warning("MP4 needs the video extra (%s not installed): writing a GIF instead (%s); for MP4: %s",
                    ", ".join(missing_packages("video")), path.with_suffix(".gif").name, install_command("video"))
        return path.with_suffix(".gif")
    return path


def write_video(frames: Sequence[np.ndarray], path: str | os.PathLike, fps: float) -> Path:
    """Write frames ([H, W, 3] uint8) atomically as MP4 or GIF (by suffix, see `video_path`)."""
    from bmimic.runs.folder import atomic_write

    path = video_path(Path(path))
    if not frames:
        raise RenderError("no frames to write")
    if path.suffix.lower() == ".mp4":
        atomic_write(path, lambda tmp: _write_mp4(frames, tmp, fps))
    else:
        atomic_write(path, lambda tmp: _write_gif(frames, tmp, fps))
    return path


def _write_mp4(frames: Sequence[np.ndarray], tmp: str, fps: float) -> None:
    import imageio.v2 as imageio

    # macro_block_size=1: keep the requested size (ffmpeg would otherwise round up to multiples of 16).
    writer: Any
    with imageio.get_writer(tmp, format="FFMPEG", fps=fps, codec="libx264", quality=8,
                            pixelformat="yuv420p", macro_block_size=1) as writer:
        for frame in frames:
            writer.append_data(frame)


def _write_gif(frames: Sequence[np.ndarray], tmp: str, fps: float) -> None:
    from PIL import Image

    images = [Image.fromarray(f).quantize(colors=256, method=Image.Quantize.FASTOCTREE) for f in frames]
    # GIF delays are whole hundredths of a second: 50 fps -> 20 ms exactly, 30 fps -> 30 ms.
    duration_ms = max(10, int(round(100.0 / fps)) * 10)
    images[0].save(tmp, format="GIF", save_all=True, append_images=images[1:], duration=duration_ms, loop=0,
                   optimize=False, disposal=1)
