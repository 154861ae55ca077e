"""faceplan's application layer: plan files, the prediction pipeline, the `faceplan` CLI,
rendering, comparison with post-operative scans.

Rendering is off-screen. Without a display, VTK's default X window would fail (with a warning)
before falling back, so the EGL window is asked for straight away (Mesa's EGL works headless).
"""
import os as _os

if not _os.environ.get("DISPLAY"):
    _os.environ.setdefault("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow")
