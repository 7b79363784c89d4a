"""Headless OpenGL through EGL (moderngl), and GLSL loading.

One standalone context per process (`gl_context()`), GL 4.3+ core so compute shaders work. It runs on Mesa's
llvmpipe as on NVIDIA's EGL. GLSL sources live in files beside the Python that runs them; `#include "name.glsl"`
lines are resolved against the including file's folder, then render/.
"""
from __future__ import annotations

import ctypes.util
import functools
import re
from pathlib import Path

import moderngl

REQUIRED_GL = 430
RENDER_DIR = Path(__file__).resolve().parent
EGL_PACKAGES = "libegl1 libgl1-mesa-dri libegl-mesa0"


class GLUnavailableError(RuntimeError):
    """Headless OpenGL could not start."""


WARM_UP_SIZE = (200, 112)
"""The size of the made-up frames a live server's spare workers and a live client run before their first session or
frame (quadcast.server.app.SessionHost, quadcast.client.quasar.QuasarClient.warm_up), so that llvmpipe compiles the
shaders before a real frame waits for them: small, and neither it nor its half (a server's hidden layers) has a side
that is a power of two. llvmpipe compiles a shader variant per state, and whether a texture's sides are powers of
two is part of it: warmed up at 64x36, a 480x270 session's first frames still waited for half of their compiling
(docs/speed.md, stop 53)."""


@functools.lru_cache(maxsize=1)
def gl_context() -> moderngl.Context:
    """The process's headless GL context (created on first use)."""
    return create_context()


def create_context() -> moderngl.Context:
    """A new headless GL context, current on the calling thread (a GL worker thread makes its own)."""
    if ctypes.util.find_library("EGL") is None:
        raise GLUnavailableError(
            f"libEGL was not found: install Debian's {EGL_PACKAGES} (make demo / make test do this as root)")
    try:
        ctx = moderngl.create_standalone_context(backend="egl", require=REQUIRED_GL)
    except Exception as exc:  # moderngl raises plain Exceptions from the EGL loader
        raise GLUnavailableError(
            f"could not create a headless GL {REQUIRED_GL // 100}.{REQUIRED_GL % 100 // 10} context through EGL "
            f"({exc}); Mesa needs {EGL_PACKAGES}") from exc
    return ctx


_INCLUDE = re.compile(r'^\s*#include\s+"([^"]+)"\s*$', re.MULTILINE)


def read_glsl(path: str | Path, _seen: tuple = ()) -> str:
    """A GLSL file's text with its `#include "x.glsl"` lines replaced by the included files."""
    path = Path(path)
    if path in _seen:
        raise ValueError(f"GLSL include cycle: {' -> '.join(str(p) for p in (*_seen, path))}")

    def include(match: re.Match) -> str:
        name = match.group(1)
        for folder in (path.parent, RENDER_DIR):
            if (folder / name).exists():
                return read_glsl(folder / name, (*_seen, path))
        raise FileNotFoundError(f"{path}: #include \"{name}\" not found beside it or in {RENDER_DIR}")

    return _INCLUDE.sub(include, path.read_text())


def _with_defines(source: str, defines: tuple) -> str:
    if not defines:
        return source
    head, rest = source.split("\n", 1)  # keep #version first
    return head + "\n" + "".join(f"#define {k} {v}\n" for k, v in defines) + rest


@functools.lru_cache(maxsize=None)
def _program_cached(ctx: moderngl.Context, vertex: Path, fragment: Path | None, defines: tuple) -> moderngl.Program:
    return ctx.program(vertex_shader=_with_defines(read_glsl(vertex), defines),
                       fragment_shader=_with_defines(read_glsl(fragment), defines) if fragment else None)


def program(ctx: moderngl.Context, vertex: str | Path, fragment: str | Path | None = None,
            **defines) -> moderngl.Program:
    """A (cached) render program from shader files, with optional `#define`s (in both stages)."""
    return _program_cached(ctx, Path(vertex).resolve(), Path(fragment).resolve() if fragment else None,
                           tuple(sorted(defines.items())))


@functools.lru_cache(maxsize=None)
def _compute_cached(ctx: moderngl.Context, path: Path, defines: tuple) -> moderngl.ComputeShader:
    return ctx.compute_shader(_with_defines(read_glsl(path), defines))


def compute(ctx: moderngl.Context, path: str | Path, **defines) -> moderngl.ComputeShader:
    """A (cached) compute shader from a `.comp` file, with optional `#define`s."""
    return _compute_cached(ctx, Path(path).resolve(), tuple(sorted(defines.items())))


@functools.lru_cache(maxsize=1)
def _copy_image_sub_data():
    """GL 4.3's glCopyImageSubData from the EGL loader (None where it cannot be found)."""
    name = ctypes.util.find_library("EGL")
    if name is None:
        return None
    egl = ctypes.CDLL(name)
    egl.eglGetProcAddress.restype = ctypes.c_void_p
    egl.eglGetProcAddress.argtypes = [ctypes.c_char_p]
    address = egl.eglGetProcAddress(b"glCopyImageSubData")
    image = [ctypes.c_uint, ctypes.c_uint, ctypes.c_int, ctypes.c_int, ctypes.c_int, ctypes.c_int]
    return ctypes.CFUNCTYPE(None, *image, *image, ctypes.c_int, ctypes.c_int, ctypes.c_int)(address) if address \
        else None


def can_copy_textures() -> bool:
    """Whether `copy_texture` works here."""
    return _copy_image_sub_data() is not None


def copy_texture(ctx: moderngl.Context, src: moderngl.Texture, dst: moderngl.Texture,
                 at: tuple[int, int] | None = None, rect: tuple[int, int, int, int] | None = None) -> None:
    """Copy a 2D texture's level 0 into another of the same size and format, depth textures too (glCopyImageSubData:
    a raw copy; moderngl has no call for it, and its copy_framebuffer leaves depth alone); with `at`, into the
    rectangle of `dst` whose lower-left texel is `at` (x, y, GL's bottom-left origin), which must lie within it. With
    `rect` (x, y, w, h, GL's origin), only that rectangle of `src`, to the same place in `dst` unless `at` is given.
    `ctx` must be current: an EGL context, as `create_context` makes (the call is looked up through EGL)."""
    if src.dtype != dst.dtype or src.depth != dst.depth or src.components != dst.components or (
            at is None and rect is None and src.size != dst.size):
        raise ValueError(f"copy_texture: need the same size and format, got {src.size} {src.dtype} and {dst.size} "
                         f"{dst.dtype}")
    sx, sy, w, h = (0, 0, *src.size) if rect is None else (int(v) for v in rect)
    if not (0 <= sx and 0 <= sy and w >= 0 and h >= 0 and sx + w <= src.size[0] and sy + h <= src.size[1]):
        raise ValueError(f"copy_texture: rect {rect} is not within the {src.size[0]}x{src.size[1]} source")
    x, y = (sx, sy) if at is None else (int(at[0]), int(at[1]))
    if not (0 <= x and 0 <= y and x + w <= dst.size[0] and y + h <= dst.size[1]):
        raise ValueError(f"copy_texture: a {w}x{h} texture at {(x, y)} does not fit in "
                         f"{dst.size[0]}x{dst.size[1]}")
    if w == 0 or h == 0:
        return
    copy = _copy_image_sub_data()
    if copy is None:
        raise GLUnavailableError("copy_texture: glCopyImageSubData is not available from EGL")
    texture_2d = 0x0DE1
    copy(src.glo, texture_2d, 0, sx, sy, 0, dst.glo, texture_2d, 0, x, y, 0, w, h, 1)


def read_buffer(buffer: moderngl.Buffer, size: int) -> bytes:
    """The first `size` bytes of a GL buffer. Zero bytes give b"" (moderngl cannot map an empty range)."""
    if size < 0 or size > buffer.size:
        raise ValueError(f"read_buffer: size {size} is outside the buffer's 0..{buffer.size} bytes")
    return buffer.read(size=size) if size else b""


def write_changed_uniforms(prog: moderngl.Program, values) -> None:
    """Write each (name, bytes) of `values` that `prog` uses, unless these bytes are what this function last wrote
    to that uniform of that program (kept in `prog.extra`): a draw loop over many objects then writes only what
    changes from one object to the next. Only for uniforms that nothing else writes."""
    written = prog.extra
    if written is None:
        written = prog.extra = {}
    for name, data in values:
        if written.get(name) != data:
            member = prog.get(name, None)
            if member is not None:
                member.write(data)
            written[name] = data


def set_uniforms(prog, **values) -> None:
    """Set the uniforms a program actually uses (the GLSL compiler drops unused ones). Looked up with
    `prog.get` (a dict lookup): `name in prog` walks all of a program's members, which cost the server about 22 ms
    a frame in the monastery (~600 draws)."""
    for name, value in values.items():
        member = prog.get(name, None)
        if member is not None:
            if isinstance(value, (bytes, bytearray)):
                member.write(value)
            else:
                member.value = value
