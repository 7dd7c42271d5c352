"""Headless OpenGL: choose EGL or OSMesa once per process and own the one GL context.

PyOpenGL binds its function pointers to a platform (EGL, OSMesa, GLX) when
`OpenGL.GL` is first imported, so the choice has to be made before any module
imports OpenGL, and a failed EGL start cannot be undone in-process. EGL is
therefore tried in a short-lived subprocess first; OSMesa is the fallback.
A PYOPENGL_PLATFORM set by the user is always respected.
"""
from __future__ import annotations

import os
import subprocess
import sys
import threading
from typing import Any

SUPPORTED = ("egl", "osmesa")
_PROBE_TIMEOUT_S = 30.0

_choice_lock = threading.Lock()
_backend: str | None = None
_backend_reason = ""

# One context serves every render; contexts are thread-bound, so renders are serialised.
render_lock = threading.RLock()
_context: Any = None

_EGL_PROBE = r"""
import os
os.environ["PYOPENGL_PLATFORM"] = "egl"
from pyrender.platforms.egl import EGLPlatform, get_default_device
p = EGLPlatform(16, 16, device=get_default_device())
p.init_context()
p.make_current()
from OpenGL import GL
# A surfaceless context has no default framebuffer: draw into a renderbuffer.
fb, rb = GL.glGenFramebuffers(1), GL.glGenRenderbuffers(1)
GL.glBindRenderbuffer(GL.GL_RENDERBUFFER, rb)
GL.glRenderbufferStorage(GL.GL_RENDERBUFFER, GL.GL_RGBA8, 8, 8)
GL.glBindFramebuffer(GL.GL_FRAMEBUFFER, fb)
GL.glFramebufferRenderbuffer(GL.GL_FRAMEBUFFER, GL.GL_COLOR_ATTACHMENT0, GL.GL_RENDERBUFFER, rb)
GL.glClearColor(0.0, 0.5, 1.0, 1.0)
GL.glClear(GL.GL_COLOR_BUFFER_BIT)
px = bytes(GL.glReadPixels(0, 0, 1, 1, GL.GL_RGBA, GL.GL_UNSIGNED_BYTE))
assert px[0] == 0 and px[2] == 255, px
p.delete_context()
"""


def _probe_egl() -> tuple[bool, str]:
    env = dict(os.environ, PYOPENGL_PLATFORM="egl")
    try:
        res = subprocess.run([sys.executable, "-c", _EGL_PROBE], env=env, capture_output=True,
                             text=True, timeout=_PROBE_TIMEOUT_S)
    except (OSError, subprocess.TimeoutExpired) as exc:
        return False, f"EGL probe did not finish: {exc}"
    if res.returncode != 0:
        last = (res.stderr.strip().splitlines() or ["no output"])[-1]
        return False, f"EGL probe failed: {last}"
    return True, "EGL probe succeeded"


def gl_backend() -> str:
    """The OpenGL platform renders use: "egl" or "osmesa" (decided once, then cached).

    Sets PYOPENGL_PLATFORM when the user has not; raises RuntimeError when OpenGL was
    already imported without a headless platform, since that cannot be changed any more.
    """
    global _backend, _backend_reason
    with _choice_lock:
        if _backend is not None:
            return _backend
        user = os.environ.get("PYOPENGL_PLATFORM", "").strip().lower()
        if user:
            if user not in SUPPORTED:
                raise RuntimeError(
                    f"PYOPENGL_PLATFORM={user!r} is not a headless platform; use one of {SUPPORTED}")
            _backend, _backend_reason = user, "set by PYOPENGL_PLATFORM"
            return _backend
        if "OpenGL.platform" in sys.modules:
            # Too late to choose: use whatever PyOpenGL already bound, if it is headless.
            bound = type(sys.modules["OpenGL.platform"].PLATFORM).__name__.lower()
            for name in SUPPORTED:
                if bound.startswith(name):
                    _backend, _backend_reason = name, "already bound by an earlier OpenGL import"
                    os.environ["PYOPENGL_PLATFORM"] = name
                    return _backend
            raise RuntimeError(
                f"OpenGL was imported (platform {bound}) before a headless platform was chosen; "
                "set PYOPENGL_PLATFORM=egl or osmesa, or call salad.render.gl_backend() before "
                "importing OpenGL or pyrender")
        ok, why = _probe_egl()
        _backend = "egl" if ok else "osmesa"
        _backend_reason = why
        os.environ["PYOPENGL_PLATFORM"] = _backend
        return _backend


def backend_reason() -> str:
    """Why gl_backend() chose what it chose (empty before the first choice)."""
    return _backend_reason


def gl_context():
    """The process-wide GL context (a pyrender platform), created on first use and made
    current in the calling thread. Call with `render_lock` held."""
    global _context
    backend = gl_backend()
    if _context is None:
        if backend == "egl":
            from pyrender.platforms.egl import EGLPlatform, get_device_by_index
            # Same device choice as pyrender's OffscreenRenderer.
            ctx = EGLPlatform(16, 16, device=get_device_by_index(int(os.environ.get("EGL_DEVICE_ID", "0"))))
        else:
            from pyrender.platforms.osmesa import OSMesaPlatform
            ctx = OSMesaPlatform(16, 16)
        try:
            ctx.init_context()
        except Exception as exc:  # the message from PyOpenGL alone rarely names the cause
            raise RuntimeError(
                f"could not create an offscreen OpenGL context with {backend} "
                f"({backend_reason()}); on Debian install libegl1 libegl-mesa0 libgl1-mesa-dri "
                f"libosmesa6: {exc}") from exc
        _context = ctx
    _context.make_current()
    return _context


def release_context() -> None:
    """Detach the context from the calling thread so another thread can make it current
    (EGL refuses a context that is still current elsewhere; pyrender never releases it)."""
    if _context is None or gl_backend() != "egl":
        return
    from OpenGL import EGL

    EGL.eglMakeCurrent(_context._egl_display, EGL.EGL_NO_SURFACE, EGL.EGL_NO_SURFACE, EGL.EGL_NO_CONTEXT)
