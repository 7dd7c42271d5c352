"""The GL side: one pyrender scene and renderer per process, fed by vertex-buffer updates.

Rebuilding pyrender meshes every frame re-uploads and re-links everything; instead
the scene keeps fixed-size meshes (floor, body, shadow) whose vertex buffers are
overwritten in place each frame, and the renderer reads back only the colour
buffer. Both rely on pyrender 0.1.45 internals (Primitive._buffers[0] holds the
interleaved [position, colour] rows; Renderer._read_main_framebuffer does the
read-back), which requirements.txt pins.
"""
from __future__ import annotations

from contextlib import contextmanager

import numpy as np

import salad.render.backend as backend
import salad.render.style as style

_engine: "Engine | None" = None
_depth = 0  # nesting of engine() in the thread holding the lock
ZNEAR, ZFAR = 0.2, 80.0


def _pyrender():
    backend.gl_backend()  # PYOPENGL_PLATFORM must be final before OpenGL is imported
    import pyrender

    return pyrender


class Engine:
    """Scene graph and renderer bound to the process-wide GL context."""

    def __init__(self):
        pyrender = _pyrender()
        from OpenGL import GL

        self._gl = GL
        self._pr = pyrender
        self.flags = pyrender.RenderFlags.FLAT | pyrender.RenderFlags.OFFSCREEN
        self.scene = pyrender.Scene(bg_color=np.append(style.BACKGROUND, 1.0).astype(float),
                                    ambient_light=np.zeros(3))
        self.camera = pyrender.PerspectiveCamera(yfov=1.0, znear=ZNEAR, zfar=ZFAR)
        self.camera_node = self.scene.add(self.camera, pose=np.eye(4))
        from .geometry import floor_mesh

        rows, faces = floor_mesh()
        self.floor_node = self.scene.add(self._mesh(rows, faces))
        self._dynamic: dict[str, tuple] = {}   # name -> (node, primitive, n_vertices, faces)
        self._static: dict[str, object] = {}   # name -> node
        self.renderer = _make_renderer()(64, 64)

    # ---------------------------------------------------------------- meshes
    def _mesh(self, rows: np.ndarray, faces: np.ndarray, blend: bool = False):
        pr = self._pr
        material = pr.MetallicRoughnessMaterial(baseColorFactor=[1.0, 1.0, 1.0, 1.0],
                                                alphaMode="BLEND" if blend else "OPAQUE",
                                                doubleSided=False)
        prim = pr.Primitive(positions=rows[:, :3], color_0=rows[:, 3:7], indices=faces,
                            material=material, mode=pr.GLTF.TRIANGLES)
        mesh = pr.Mesh([prim])
        # Bounds are never needed (no shadow maps) and pyrender's own code for them
        # uses a NumPy alias removed in NumPy 2.
        mesh._bounds = np.array([rows[:, :3].min(0), rows[:, :3].max(0)]) if len(rows) else np.zeros((2, 3))
        return mesh

    def set_dynamic(self, name: str, n_vertices: int, faces: np.ndarray, blend: bool = False) -> None:
        """Keep a mesh with this many vertices and these faces; its vertices come per frame."""
        have = self._dynamic.get(name)
        if have is not None and have[2] == n_vertices and np.array_equal(have[3], faces):
            return
        self.drop(name)
        if n_vertices == 0:
            return
        rows = np.zeros((n_vertices, 7), np.float32)
        # pyrender decides once, from the initial colours, whether a mesh is blended
        # (drawn after all opaque ones); a blended mesh drawn too early hides the floor.
        rows[:, 6] = 0.0 if blend else 1.0
        mesh = self._mesh(rows, faces, blend)
        prim = mesh.primitives[0]
        # The per-frame upload writes [x y z r g b a] rows straight into the vertex buffer.
        if prim.buf_flags != (self._pr.constants.BufFlags.POSITION | self._pr.constants.BufFlags.COLOR_0):
            raise RuntimeError(f"unexpected pyrender vertex layout {prim.buf_flags} for {name}")
        node = self.scene.add(mesh)
        self._dynamic[name] = (node, prim, n_vertices, faces)

    def set_static(self, name: str, rows: np.ndarray | None, faces: np.ndarray | None) -> None:
        self.drop(name)
        if rows is not None and len(rows) and len(faces):
            self._static[name] = self.scene.add(self._mesh(rows, faces))

    def drop(self, name: str) -> None:
        if name in self._dynamic:
            self.scene.remove_node(self._dynamic.pop(name)[0])
        if name in self._static:
            self.scene.remove_node(self._static.pop(name))

    # ---------------------------------------------------------------- drawing
    def draw(self, size: tuple[int, int], yfov: float, cam_pose: np.ndarray, floor_shift: np.ndarray,
             vertices: dict[str, np.ndarray]) -> np.ndarray:
        """One frame as (H, W, 3) uint8. `vertices` maps dynamic mesh names to rows (V, 7)."""
        GL = self._gl
        w, h = size
        r = self.renderer
        r.viewport_width, r.viewport_height = w, h
        self.camera.yfov = float(yfov)
        self.camera.aspectRatio = w / h
        self.scene.set_pose(self.camera_node, cam_pose)
        pose = np.eye(4)
        pose[[0, 2], 3] = floor_shift
        self.scene.set_pose(self.floor_node, pose)
        r._update_context(self.scene, self.flags)  # puts newly added meshes on the GPU
        for name, rows in vertices.items():
            _, prim, n, _ = self._dynamic[name]
            if rows.shape != (n, 7):
                raise AssertionError(f"{name}: expected {(n, 7)} vertex rows, got {rows.shape}")
            GL.glBindBuffer(GL.GL_ARRAY_BUFFER, prim._buffers[0])
            GL.glBufferSubData(GL.GL_ARRAY_BUFFER, 0, rows.nbytes, np.ascontiguousarray(rows, np.float32))
        GL.glBindBuffer(GL.GL_ARRAY_BUFFER, 0)
        return r.render(self.scene, self.flags)


def _make_renderer():
    pr = _pyrender()
    from OpenGL import GL
    from pyrender.shader_program import ShaderProgramCache

    class ProgramCache(ShaderProgramCache):
        """pyrender keys its shader cache on the current context object, and PyOpenGL's
        OSMesa context handles compare unequal to themselves, so under OSMesa every frame
        recompiled (and leaked) its shaders. There is a single context here: key on the
        shaders alone."""

        def __init__(self):
            super().__init__()
            self._by_shaders = {}

        def get_program(self, vertex_shader, fragment_shader, geometry_shader=None, defines=None):
            key = (vertex_shader, fragment_shader, geometry_shader, tuple(sorted((defines or {}).items())))
            if key not in self._by_shaders:
                self._by_shaders[key] = super().get_program(vertex_shader, fragment_shader,
                                                            geometry_shader, defines)
            return self._by_shaders[key]

        def clear(self):
            super().clear()
            self._by_shaders = {}

    class ColorOnly(pr.Renderer):
        """Resolves the multisampled colour buffer and reads it back, skipping pyrender's
        depth read-back and conversion, which cost as much as the drawing itself.

        `samples` replaces pyrender's fixed 4x MSAA: in a software GL the resolve is a large
        share of a frame, so previews render with fewer samples (0: none, read straight from
        the draw buffer)."""

        def __init__(self, width, height):
            super().__init__(width, height)
            self._program_cache = ProgramCache()
            self.samples = style.MSAA_SAMPLES
            self._ms_config = None      # (width, height, samples) the draw buffers were allocated for

        def _configure_main_framebuffer(self):
            super()._configure_main_framebuffer()
            config = (*self._main_fb_dims, self.samples)
            if config == self._ms_config or (self._ms_config is None and self.samples == 4):
                self._ms_config = config
                return
            w, h = self._main_fb_dims
            for buf, fmt in ((self._main_cb_ms, GL.GL_RGBA), (self._main_db_ms, GL.GL_DEPTH_COMPONENT24)):
                GL.glBindRenderbuffer(GL.GL_RENDERBUFFER, buf)
                GL.glRenderbufferStorageMultisample(GL.GL_RENDERBUFFER, self.samples, fmt, w, h)
            self._ms_config = config

        def _read_main_framebuffer(self, scene, flags):
            w, h = self._main_fb_dims
            if self.samples:
                GL.glBindFramebuffer(GL.GL_READ_FRAMEBUFFER, self._main_fb_ms)
                GL.glBindFramebuffer(GL.GL_DRAW_FRAMEBUFFER, self._main_fb)
                GL.glBlitFramebuffer(0, 0, w, h, 0, 0, w, h, GL.GL_COLOR_BUFFER_BIT, GL.GL_LINEAR)
                GL.glBindFramebuffer(GL.GL_READ_FRAMEBUFFER, self._main_fb)
            else:
                GL.glBindFramebuffer(GL.GL_READ_FRAMEBUFFER, self._main_fb_ms)
            GL.glPixelStorei(GL.GL_PACK_ALIGNMENT, 1)
            buf = GL.glReadPixels(0, 0, w, h, GL.GL_RGB, GL.GL_UNSIGNED_BYTE)
            img = np.frombuffer(buf, dtype=np.uint8).reshape(h, w, 3)
            return img[::-1]

    return ColorOnly


@contextmanager
def engine():
    """The process-wide Engine with its GL context current and exclusively held."""
    global _engine, _depth
    with backend.render_lock:
        if _depth == 0:
            backend.gl_context()
        _depth += 1
        try:
            if _engine is None:
                _engine = Engine()
            yield _engine
        finally:
            _depth -= 1
            if _depth == 0:
                backend.release_context()
