"""The ``reblur`` command line: a thin layer over the library.

Each command resolves paths, opens the inputs with :mod:`reblur.io`, calls one library
function with its options passed 1:1 as keywords, and writes with :mod:`reblur.report`.

Errors never show a traceback (unless ``-v``): every failure prints one line
``reblur: error: <what went wrong>`` on stderr and exits non-zero (2 for usage errors,
1 otherwise).  Nothing is written to the output directory unless the command succeeds:
each command writes its files into a temporary sibling directory that replaces the output
directory at the end, holding its lock meanwhile (:func:`reblur.outdir.output_set`).
"""

from __future__ import annotations

import atexit
import dataclasses
import gc
import glob
import json
import logging
import math
import os
import shutil
import sys
import tempfile
import time
import traceback
from collections.abc import Callable
from pathlib import Path
from typing import Any

import click
import numpy as np

from ._memory import retain_freed_memory
from .io import (
    DEFAULT_MAX_PIXELS,
    Image,
    InputError,
    check_sizes,
    display_path,
    open_image,
    read_mask,
    reconcile_bands,
    zarr_masks,
)
from .outdir import output_set

__all__ = ["main"]

log = logging.getLogger("reblur")

#: Verbosity of the running command (read by the error handler of :func:`main`).
_STATE: dict[str, int] = {"verbose": 0}

#: Above this many observation pixels the full-size masks are kept in a zarr store on disk.
LARGE_MASK_PIXELS = 64_000_000
#: Most tile threads (or processes) ``reblur detect`` starts by default: each holds its
#: tiles' buffers (a 100 MP pair: peak RSS 777 MB with one, 956 MB with two), so more
#: cores buy time with memory.
DEFAULT_WORKERS_MAX = 4


def default_workers() -> int:
    """Tile workers when ``--workers`` is not given: the CPUs this process may use, at
    most :data:`DEFAULT_WORKERS_MAX` (the tiles' results do not depend on it)."""
    from ._memory import available_cpus

    return min(DEFAULT_WORKERS_MAX, available_cpus())


#: Files ``reblur simulate`` writes.
SIMULATE_NAMES = ("reference.tif", "observed.tif", "truth.png", "unknown.png", "path.json")


# ---------------------------------------------------------------------------- errors
def _one_line(text: str) -> str:
    return " ".join(str(text).split())


def _describe(exc: BaseException) -> str:
    """One line describing an exception raised while running a command."""
    if isinstance(exc, (InputError, ValueError)):
        return _one_line(str(exc)) or type(exc).__name__
    if isinstance(exc, MemoryError):
        return "out of memory (try a smaller --tile-size, or fewer --workers)"
    if isinstance(exc, OSError):
        where = f"{_show(exc.filename)}: " if exc.filename else ""
        return _one_line(f"{where}{exc.strerror or exc}")
    name = type(exc).__name__
    if type(exc).__module__.startswith("reblur"):
        return _one_line(f"{name}: {exc}")
    return _one_line(f"internal error: {name}: {exc} (run with -v for the traceback)")


def _fail(message: str, code: int) -> None:
    # paths in messages are escaped where they are written (display_path); what is left
    # non-printable (a library's message quoting a file name) is escaped here
    click.echo(f"reblur: error: {display_path(_one_line(message))}", err=True)
    sys.exit(code)


def _show(path: Any) -> str:
    """A path as printed in messages: non-printable characters escaped (:func:`display_path`)."""
    return display_path(path)


class _PrintableFormatter(logging.Formatter):
    """Log lines with non-printable characters of the message escaped (a file name with a
    newline or a terminal escape sequence stays one inert line); tracebacks unchanged."""

    def formatMessage(self, record: logging.LogRecord) -> str:
        record.message = display_path(record.message)
        return super().formatMessage(record)


class _Interrupted(Exception):
    """A KeyboardInterrupt (Ctrl-C) that ended a command, past click's own handler (which
    would turn it into ``Abort`` and print a blank line)."""


class _ReblurGroup(click.Group):
    """Click group whose errors are one line on stderr, with a traceback only under -v.

    Ctrl-C exits 130 with "interrupted" (the shell's convention for SIGINT), after the
    command's own clean-up (:func:`reblur.outdir.output_set` removes its temporaries).
    """

    def invoke(self, ctx: click.Context) -> Any:
        try:
            return super().invoke(ctx)
        except KeyboardInterrupt:
            raise _Interrupted() from None

    def main(self, args=None, prog_name=None, complete_var=None, standalone_mode=True, **extra):
        if not standalone_mode:
            return super().main(args, prog_name, complete_var, standalone_mode=False, **extra)
        try:
            rv = super().main(
                args, prog_name or "reblur", complete_var, standalone_mode=False, **extra
            )
        except click.exceptions.Abort as exc:
            if isinstance(exc.__cause__, KeyboardInterrupt):  # Ctrl-C while parsing
                _fail("interrupted", 130)
            _fail("aborted", 1)
        except click.UsageError as exc:
            cmd = exc.ctx.command_path if exc.ctx is not None else "reblur"
            _fail(f"{exc.format_message()} (see '{cmd} --help')", exc.exit_code)
        except click.ClickException as exc:
            _fail(exc.format_message(), exc.exit_code)
        except (KeyboardInterrupt, _Interrupted):
            _fail("interrupted", 130)
        except Exception as exc:  # noqa: BLE001 - the one place every error is reported
            if _STATE["verbose"]:
                traceback.print_exc()
            _fail(_describe(exc), 1)
        sys.exit(rv if isinstance(rv, int) else 0)


# ---------------------------------------------------------------------------- options
class _Finite(click.FloatRange):
    """A float option that must be finite (no nan, inf; nan allowed with ``allow_nan``)
    and within its range."""

    name = "float"

    def __init__(self, *args: Any, allow_nan: bool = False, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.allow_nan = allow_nan

    def convert(self, value: Any, param: click.Parameter | None,
                ctx: click.Context | None) -> float:
        number = click.FLOAT.convert(value, param, ctx)
        if self.allow_nan and math.isnan(number):
            return number
        if not math.isfinite(number):
            self.fail(f"{value!r} is not a finite number.", param, ctx)
        return super().convert(number, param, ctx)


def _check_grid(t_max: int, rz_max: float, rz_step: float | None) -> None:
    """Refuse a pose grid over the budget before any input is read (its size does not depend
    on the images when the rotation step is given)."""
    if rz_step is None:
        return
    from .grid import grid_size_for

    try:
        grid_size_for((1, 1), t_max=t_max, rz_max=rz_max, rz_step=rz_step)
    except ValueError as exc:
        raise click.BadParameter(str(exc).replace("rz_step", "--rz-step").replace(
            "rz_max", "--rz-max").replace("t_max", "--t-max"),
            param_hint="'--rz-step' / '--rz-max' / '--t-max'") from None


def _check_scheduler(ctx: click.Context, param: click.Parameter, value: str | None):
    if value is None:
        return None
    from .dask_backend import scheduler_kind

    try:
        scheduler_kind(value)
    except (ValueError, TypeError) as exc:
        raise click.BadParameter(str(exc)) from None
    return value


def _read_hint(ctx: click.Context, param: click.Parameter, value: Path | None):
    """The ``--align-hint`` file: 9 finite numbers (a 3x3 reference -> observation
    homography in full-resolution pixels, row by row) as JSON (a nested or flat list, or
    an object with an ``"H"`` entry) or as text (whitespace or commas; ``#`` comments);
    invertible.  Returns it normalised (``H[2, 2] = 1``)."""
    if value is None:
        return None
    import numpy as np

    name = display_path(value)
    want = "a 3x3 reference -> observation homography in full-resolution pixels, row by row"
    try:
        text = value.read_text()
    except (OSError, UnicodeDecodeError) as exc:
        why = "not a text file" if isinstance(exc, UnicodeDecodeError) else (
            "no such file" if isinstance(exc, FileNotFoundError) else exc.strerror or exc)
        raise click.BadParameter(f"{name}: {why}; give {want}") from None
    try:
        data = json.loads(text)
        if isinstance(data, dict):
            data = data.get("H", data.get("homography"))
    except ValueError:
        lines = (line.split("#", 1)[0] for line in text.splitlines())
        data = " ".join(lines).replace(",", " ").replace("[", " ").replace("]", " ").split()
    try:
        H = np.array(data, dtype=np.float64).ravel()
    except (TypeError, ValueError):
        raise click.BadParameter(f"{name}: not a list of numbers; give {want}") from None
    if H.size != 9:
        raise click.BadParameter(f"{name}: {H.size} numbers, expected 9 ({want})")
    if not np.all(np.isfinite(H)):
        raise click.BadParameter(f"{name}: the homography has non-finite numbers; give {want}")
    H = H.reshape(3, 3)
    if H[2, 2] == 0 or abs(np.linalg.det(H / H[2, 2])) < 1e-12:
        raise click.BadParameter(f"{name}: the homography is singular (not invertible); "
                                 f"give {want}")
    return H / H[2, 2]


def _quiet_unraisable(unraisable: Any) -> None:
    """``sys.unraisablehook`` without -v: what a library could not raise (a coroutine
    garbage-collected at exit) is logged at debug level, not printed."""
    log.debug("ignored in %r: %s", unraisable.object, unraisable.exc_value)


def _set_verbosity(ctx: click.Context, param: click.Parameter, value: int) -> int:
    _STATE["verbose"] = max(_STATE["verbose"], int(value or 0))
    level = (logging.WARNING, logging.INFO, logging.DEBUG)[min(_STATE["verbose"], 2)]
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(_PrintableFormatter("reblur: %(levelname)s: %(message)s"))
    root = logging.getLogger()
    root.handlers[:] = [handler]
    root.setLevel(level)
    logging.captureWarnings(True)
    # third-party warnings only with -v: without it, stderr carries at most the error line
    logging.getLogger("py.warnings").setLevel(logging.WARNING if _STATE["verbose"]
                                              else logging.ERROR)
    for noisy in ("rasterio", "matplotlib", "PIL", "tifffile", "numcodecs", "zarr",
                  "imagecodecs"):
        logging.getLogger(noisy).setLevel(logging.WARNING if _STATE["verbose"] >= 2
                                          else logging.ERROR)
    # zarr's event loop, torn down at exit after a failed read, reports its pending tasks
    # ("Task was destroyed but it is pending!", with their stacks): only with -v
    logging.getLogger("asyncio").setLevel(logging.ERROR if _STATE["verbose"]
                                          else logging.CRITICAL + 1)
    # ... and the coroutines it drops then ("Exception ignored in: <coroutine ...>")
    sys.unraisablehook = sys.__unraisablehook__ if _STATE["verbose"] else _quiet_unraisable
    return value


def verbose_option(f: Callable) -> Callable:
    """``-v/--verbose`` (count): more log output and tracebacks on error."""
    return click.option(
        "-v", "--verbose", count=True, expose_value=False, is_eager=True,
        callback=_set_verbosity,
        help="Log more (-vv: debug); show the traceback on error.",
    )(f)


def quiet_option(f: Callable) -> Callable:
    return click.option("-q", "--quiet", is_flag=True, help="No progress bars.")(f)


def overwrite_option(f: Callable) -> Callable:
    return click.option(
        "--overwrite", is_flag=True,
        help="Replace the results of an earlier run in the output directory.",
    )(f)


def max_pixels_option(default: int) -> Callable:
    return click.option(
        "--max-pixels", type=click.IntRange(min=1), default=default, show_default=True,
        help="Refuse larger images (height x width), or images decoding to more than 4 "
             "bytes per allowed pixel: a guard against decompression bombs.",
    )


_PATH = click.Path(path_type=Path)


def _stderr_is_terminal() -> bool:
    try:
        return sys.stderr.isatty()
    except (AttributeError, ValueError):  # replaced or closed stream
        return False


class _Progress:
    """``progress(stage, fraction)`` callback for the stages of a run.

    On a terminal: one tqdm bar per stage on stderr.  Otherwise (a batch job, a log file):
    a line ``reblur: [PREFIX]STAGE: N % (S s)`` each time a stage passes another ``step``
    (10 %), its start and its end included.
    """

    def __init__(self, prefix: str = "", step: int = 10) -> None:
        self.bar = None
        self.stage: str | None = None
        self.prefix = prefix
        self.step = int(step)
        self.tty = _stderr_is_terminal()
        self.shown = -1
        self.t_stage = time.perf_counter()

    def __call__(self, stage: str, fraction: float) -> None:
        n = int(round(100 * min(max(float(fraction), 0.0), 1.0)))
        if stage != self.stage:
            self.close()
            self.stage = stage
            self.shown = -1
            self.t_stage = time.perf_counter()
            if self.tty:
                from tqdm import tqdm

                self.bar = tqdm(total=100, desc=self.prefix + stage, file=sys.stderr,
                                leave=False, unit="%",
                                bar_format="{desc}: {percentage:3.0f}%|{bar}| {elapsed}")
        if self.bar is not None:
            if n > self.bar.n:
                self.bar.update(n - self.bar.n)
            return
        if not self.tty:
            level = n - n % self.step
            if level > self.shown:
                self.shown = level
                click.echo(display_path(f"reblur: {self.prefix}{stage}: {level} % "
                                        f"({time.perf_counter() - self.t_stage:.1f} s)"),
                           err=True)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()
            self.bar = None


# ---------------------------------------------------------------------------- paths
def _same_or_inside(a: Path, b: Path) -> bool:
    """True when ``a`` is ``b`` or lies inside ``b``."""
    return a == b or b in a.parents


def _resolve(path: Path) -> Path:
    """``path`` made absolute with its symlinks resolved; a loop is one clear error."""
    try:
        return path.expanduser().resolve()
    except (RuntimeError, OSError) as exc:  # 3.11: RuntimeError("Symlink loop from ...")
        raise click.ClickException(
            f"{_show(path)}: symlink loop: the path cannot be resolved") from exc


def _clobbered(out_r: Path, p_r: Path, names: tuple[str, ...],
               sub_names: tuple[str, ...]) -> bool:
    """Whether the input ``p_r`` is (inside) an output ``OUT/NAME`` (``names``) or
    ``OUT/FOLDER/NAME`` (``sub_names``, in any sub-folder) that a run replaces."""
    try:
        rel = p_r.relative_to(out_r).parts
    except ValueError:
        return False
    return bool(rel) and (rel[0] in names or (len(rel) >= 2 and rel[1] in sub_names))


def _check_output_dir(
    out: Path, inputs: list[Path], names: tuple[str, ...], overwrite: bool,
    sub_names: tuple[str, ...] = (),
) -> Path:
    """Refuse output directories that are unusable, hold results, or would clobber inputs.

    ``names`` are the outputs written into ``out``, ``sub_names`` those written into its
    sub-folders (one per observation: their names are only known as the run goes, so an
    input inside such an output of any sub-folder is refused).  Writes nothing: a missing
    directory is created (to prove it can be) and removed again.
    """
    out_r = _resolve(out)
    for p in inputs:
        p_r = _resolve(p)
        if _same_or_inside(out_r, p_r):
            raise click.ClickException(
                f"{_show(out)}: output directory is (inside) the input {_show(p)}")
        if _clobbered(out_r, p_r, names, sub_names):
            raise click.ClickException(f"{_show(out)}: writing results there would overwrite "
                                       f"the input {_show(p)}; choose another --out")
    if out_r.exists():
        if not out_r.is_dir():
            raise click.ClickException(f"{_show(out)}: exists and is not a directory")
        found = [n for n in names if (out_r / n).exists()]
        if sub_names:  # an earlier many-observation run's folders (stopped before its index)
            found += sorted(f"{d.name}/" for d in out_r.iterdir()
                            if d.is_dir() and (d / "report.json").exists())
        if found and not overwrite:
            raise click.ClickException(
                f"{_show(out)}: already holds results ({', '.join(found[:3])}"
                f"{', ...' if len(found) > 3 else ''}); use --overwrite to replace them"
            )
        try:
            fd, tmp = tempfile.mkstemp(dir=out_r, prefix=".reblur-probe-")
            os.close(fd)
            os.unlink(tmp)
        except OSError as exc:
            raise click.ClickException(
                f"{_show(out)}: output directory is not writable ({exc.strerror or exc})"
            ) from exc
        return out_r
    anc = out_r
    while not anc.exists():
        anc = anc.parent
    if not anc.is_dir():
        raise click.ClickException(
            f"{_show(out)}: cannot create the output directory ({_show(anc)} is a file)")
    try:
        out_r.mkdir(parents=True)
    except OSError as exc:
        raise click.ClickException(
            f"{_show(out)}: cannot create the output directory ({exc.strerror or exc})"
        ) from exc
    # remove what the probe created, deepest first
    d = out_r
    while d != anc:
        d.rmdir()
        d = d.parent
    return out_r


def _open_pair(reference: Path, observed: Path, max_pixels: int,
               nodata: float | None = None) -> tuple[Image, Image]:
    ref = open_image(reference, max_pixels=max_pixels, nodata=nodata)
    obs = open_image(observed, max_pixels=max_pixels, nodata=nodata)
    for note_img in (ref, obs):
        for note in note_img.notes:
            log.info("%s: %s", note_img.name, note)
    check_sizes(ref, obs)
    return reconcile_bands(ref, obs)


#: Files moved into an output directory last (and removed first) when it is filled file by file.
REPORT_NAMES = ("report.html", "report.json")


def _writing(out: Path):
    """Turn a failure to write the results into one line naming the output directory."""
    import contextlib

    @contextlib.contextmanager
    def guard():
        try:
            yield
        except OSError as exc:
            if exc.errno is None:
                raise
            raise click.ClickException(
                f"{_show(out)}: cannot write the results ({exc.strerror or exc}); nothing was "
                "written"
            ) from exc

    return guard()


# ---------------------------------------------------------------------------- commands
@click.group(cls=_ReblurGroup, context_settings=dict(help_option_names=["-h", "--help"]))
@click.version_option(package_name="reblur", prog_name="reblur")
def main() -> None:
    """Change detection between a sharp reference image and a later, motion-blurred,
    re-viewpointed observation, for images up to gigapixels.

    Run 'reblur demo' for a first look, 'reblur COMMAND --help' for each command.
    """
    _quiet_libtiff()


def run(args: list[str] | None = None, **kwargs) -> Any:
    """The ``reblur`` command (its console script and ``python -m reblur``): :func:`main`
    in a process of its own, whose allocator keeps freed memory for the later stages
    (:func:`reblur._memory.retain_freed_memory`), and whose exit skips the interpreter's
    last garbage collections (:func:`_exit_without_collecting`).  :func:`main` called in
    a host's process (a test, a notebook) leaves that process's allocator and collector
    as they are.

    ``kwargs`` go to :func:`main` (click's ``standalone_mode`` ...).
    """
    retain_freed_memory()  # this process is the command's: later stages reuse pages
    atexit.unregister(_exit_without_collecting)  # once, however many runs
    atexit.register(_exit_without_collecting)
    return main(args=args, prog_name="reblur", **kwargs)


def _exit_without_collecting() -> None:
    """At the command's exit: every object then alive is frozen out of the collector
    (:func:`gc.freeze`), so the collections the interpreter runs while it tears its modules
    down do not traverse them all again: a 1 MP ``reblur detect`` (some 70,000 objects)
    took 0.23-0.33 s from its exit handlers to its end, 0.055-0.068 s frozen (``os._exit``:
    0.031-0.042 s, without the exit handlers).  Nothing is left unwritten: the outputs are
    complete and closed before :func:`main` returns, the exit handlers registered before
    this one still run after it (logging's flush, Dask's shutdown, ``weakref.finalize``),
    and objects freed by reference count are freed as before; only objects in reference
    cycles are left to the process's end."""
    gc.freeze()


def _quiet_libtiff() -> bool:
    """Stop GDAL's libtiff from printing its own error lines on stderr.

    GDAL reports a failed TIFF write (a full disk) as an error, which the command turns
    into its one line; libtiff's global default handler prints the same failure again
    ("_tiffWriteProc: No space left on device.") for the calls GDAL makes without a
    per-file handler.  The handler is cleared in the libtiff that rasterio's GDAL loads
    (the wheel's own copy); nothing happens where it cannot be found.

    Returns
    -------
    bool
        True if the handlers were cleared.
    """
    import ctypes
    import glob

    try:
        import rasterio
    except ImportError:
        return False
    libs = os.path.join(os.path.dirname(os.path.dirname(rasterio.__file__)), "rasterio.libs")
    found = sorted(glob.glob(os.path.join(libs, "libtiff*.so*")))
    if not found:
        return False
    try:
        tiff = ctypes.CDLL(found[0])
        tiff.TIFFSetErrorHandler(None)
        tiff.TIFFSetWarningHandler(None)
    except (OSError, AttributeError):
        return False
    return True


def _read_boxes(ctx: click.Context, param: click.Parameter, value: tuple[str, ...]):
    """``--box Y0,X0,H,W`` (repeatable) -> list of int tuples, or None."""
    if not value:
        return None
    boxes = []
    for text in value:
        parts = text.replace(" ", "").split(",")
        try:
            box = tuple(int(v) for v in parts)
        except ValueError:
            box = ()
        if len(box) != 4 or box[0] < 0 or box[1] < 0 or box[2] < 8 or box[3] < 8:
            raise click.BadParameter(f"{text!r}: give Y0,X0,H,W in pixels (whole numbers, "
                                     "Y0, X0 >= 0, H, W >= 8)")
        boxes.append(box)
    return boxes


def _read_config(ctx: click.Context, param: click.Parameter, value: Path | None):
    """``--config FILE``: a :class:`reblur.config.RunConfig`, or one line and exit 2."""
    from .config import ConfigError, RunConfig, load_config

    if value is None:
        return RunConfig()
    try:
        return load_config(value)
    except ConfigError as exc:
        raise click.BadParameter(str(exc)) from None


def _read_frames(ctx: click.Context, param: click.Parameter, value: str | None):
    if value is None:
        return None
    from .many import parse_frames

    try:
        return parse_frames(value)
    except ValueError as exc:
        raise click.BadParameter(str(exc)) from None


@main.command(short_help="Detect changes between a reference and blurred observations.")
@click.argument("reference", type=_PATH)
@click.argument("observed", type=_PATH, nargs=-1, required=True, metavar="OBSERVED...")
@click.option("-o", "--out", type=_PATH, required=True,
              help="Output directory (created; must not hold results unless --overwrite).")
@click.option("--t-max", type=click.IntRange(min=0), default=12, show_default=True,
              help="Pose grid: largest in-plane translation |tx|, |ty| (pixels) to start "
                   "from; the estimate widens it (up to 4x, [select] t_grow) when the blur "
                   "piles on its edge and the wider grid fits better, or starts wider when "
                   "the alignment found the blur reaching beyond it.")
@click.option("--rz-max", type=_Finite(min=0, max=45), default=3.0, show_default=True,
              help="Pose grid: largest in-plane rotation |rz| (degrees, at most 45).")
@click.option("--rz-step", type=_Finite(min=0, min_open=True, max=45), default=None,
              help="Pose grid: rotation step (degrees).  Default: the step that moves the "
                   "farthest pixel by one pixel (0.5 deg is the paper's, too coarse for "
                   "large images).")
@click.option("--lam", type=_Finite(min=0, min_open=True, max=1000), default=0.1,
              show_default=True,
              help="l1 weight lambda of the joint blur/change estimate (intensities in [0, 1]; "
                   "at most 1000).")
@click.option("--tile-size", type=click.IntRange(min=64), default=1024, show_default=True,
              help="Tile side (pixels) for reblurring and deciding; bounds the memory.")
@click.option("--threshold", type=_Finite(min=0, min_open=True), default=None,
              help="Decision threshold (> 0); default: chosen from the data.")
@click.option("--truth", type=_PATH, default=None,
              help="True change mask (non-zero = change): scores go into report.json.")
@click.option("--illumination", type=click.Choice(["auto", "global", "field"]),
              default=None,
              help="Photometric model: one gain and offset per band, a smooth field "
                   "(ramps, vignetting, shadow gradients), or chosen from the data "
                   "(default: auto, or the --config file's [decision] illumination).")
@click.option("--nodata", type=_Finite(allow_nan=True), default=None, metavar="VALUE",
              help="Pixels whose every band equals VALUE ('nan': any band not finite) "
                   "hold no data in either image: unknown, never change.  Default: what "
                   "each file declares (GeoTIFF nodata or mask, alpha band, zarr "
                   "'nodata' attribute).")
@click.option("--shutter", type=click.Choice(["global", "rolling", "auto"]), default="global",
              show_default=True,
              help="Shutter model: global, rolling (row bands with their own motion, for "
                   "CMOS cameras) or chosen from the data (rolling only when it explains "
                   "the estimation windows clearly better).")
@click.option("--grid", "grid_kind", type=click.Choice(["3d", "6d"]), default="3d",
              show_default=True,
              help="Pose grid: 3d (tx, ty, rz: the paper's) or 6d (also the scale change tz "
                   "and the tilt and pan rx, ry, about a camera of focal length --focal).")
@click.option("--focal", type=_Finite(min=0, min_open=True), default=None, metavar="PX",
              help="--grid 6d: focal length in pixels.  Default: from OBSERVED's EXIF "
                   "FocalLengthIn35mmFilm (f35 x diagonal / 43.27 mm), else 1.2 x its "
                   "long side.")
@click.option("--tz-max", type=_Finite(min=0, max=0.5), default=None,
              help="--grid 6d: largest relative scale change (default 0.002).")
@click.option("--tz-step", type=_Finite(min=0, min_open=True, max=0.5), default=None,
              help="--grid 6d: scale step (default: one pixel at the farthest pixel).")
@click.option("--tilt-max", type=_Finite(min=0, max=10), default=None,
              help="--grid 6d: largest tilt / pan |rx|, |ry| (degrees; default 0.15).")
@click.option("--tilt-step", type=_Finite(min=0, min_open=True, max=10), default=None,
              help="--grid 6d: tilt / pan step (degrees; default: one pixel at the "
                   "farthest pixel beyond the shift of the centre).")
@click.option("--no-align", is_flag=True,
              help="Skip the coarse alignment: the images are already registered (same "
                   "frame, up to the pose grid's --t-max / --rz-max).")
@click.option("--align-hint", type=_PATH, default=None, callback=_read_hint, metavar="FILE",
              help="A rough reference -> observation homography (3x3 numbers in "
                   "full-resolution pixels, row by row; text or JSON) that seeds the coarse "
                   "alignment: it reaches pairs the alignment refuses on its own (large "
                   "rotations, captures years apart).")
@click.option("--no-refine", is_flag=True,
              help="Skip the geometric refinement of the alignment after the motion "
                   "estimate (probe windows over the whole image).")
@click.option("--no-field", is_flag=True,
              help="Skip the local displacement field after the refinement (tie "
                   "points on a lattice, a smooth field for parallax and lens "
                   "distortion).")
@click.option("--windows", type=click.IntRange(min=1, max=16), default=None,
              help="Estimation windows estimated jointly (1: the paper's Algorithm 1).  "
                   "Default: 2, 4 above --large-side px, 5 above 16384 px.")
@click.option("--box", "boxes", multiple=True, callback=_read_boxes, metavar="Y0,X0,H,W",
              help="Estimate the motion on this window of OBSERVED (pixels; repeat for "
                   "several) instead of choosing windows.")
@click.option("--large-side", type=click.IntRange(min=64), default=2500, show_default=True,
              help="Long side (px) above which the large-image defaults apply.")
@click.option("--config", type=_PATH, default=None, callback=_read_config, metavar="FILE",
              help="TOML file of options: tables [decision], [select], [align], [rolling] "
                   "whose keys are the fields of DecisionParams, SelectParams, AlignParams, "
                   "RollingParams.  Flags given on the command line take precedence.")
@click.option("--every", type=click.IntRange(min=1), default=None, metavar="N",
              help="Video OBSERVED: compare every N-th frame (default: every frame).")
@click.option("--frames", default=None, callback=_read_frames, metavar="A:B",
              help="Video OBSERVED: frames A to B-1 (0-based; 'A:' to the end, ':B' from "
                   "the start).")
@max_pixels_option(DEFAULT_MAX_PIXELS)
@click.option("--workers", type=click.IntRange(min=1), default=None,
              help="Threads for the tiled stages (processes with --scheduler processes).  "
                   f"Default: the CPUs this process may use, at most {DEFAULT_WORKERS_MAX}.")
@click.option("--scheduler", default=None, callback=_check_scheduler, metavar="SCHEDULER",
              help="Run the tiled reblur-and-decide stage on Dask: 'threads', 'processes' "
                   "or the address of a running Dask scheduler (tcp://host:port), whose "
                   "workers must see the input files and the output directory.  Default: "
                   "the local thread pool.")
@overwrite_option
@quiet_option
@verbose_option
def detect(reference: Path, observed: tuple[Path, ...], out: Path, t_max: int, rz_max: float,
           rz_step: float | None, lam: float, tile_size: int, threshold: float | None,
           truth: Path | None, illumination: str | None, nodata: float | None, shutter: str,
           no_align: bool, align_hint: Any, no_refine: bool, no_field: bool,
           grid_kind: str, focal: float | None, tz_max: float | None, tz_step: float | None,
           tilt_max: float | None, tilt_step: float | None, windows: int | None,
           boxes: list | None, large_side: int, config: Any, every: int | None,
           frames: tuple[int, int | None] | None, max_pixels: int, workers: int | None,
           scheduler: str | None, overwrite: bool, quiet: bool) -> None:
    """Find what changed between REFERENCE (sharp) and OBSERVED (later, blurred).

    Inputs: PNG, JPEG, TIFF/BigTIFF/GeoTIFF or zarr; uint8, uint16 or float; gray, RGB
    (an RGB/gray pair is compared in gray; transparent alpha is no data) or multi-band.  Large TIFF
    and zarr inputs are read window by window.

    Writes into --out: changes.png (255 = change, in OBSERVED's frame), unknown.png,
    reblurred.tif, overlay.png, motion.png, report.json, report.html, and for large or
    georeferenced inputs changes.tif and unknown.tif (the TIFFs are Cloud-Optimised
    GeoTIFFs) and changes.geojson (and changes.gpkg with reblur[geo]).  Prints one
    summary line.

    Several observations (files, folders of images, glob patterns, videos read frame by
    frame): each gets its own folder OUT/NAME with those files, and OUT/index.html and
    OUT/summary.csv list them all; the reference's own work is done once.  An observation
    that fails is listed with its reason and the run goes on (the exit code is then 1).
    """
    from .many import observation_sources

    t0 = time.perf_counter()
    ctx = click.get_current_context()
    _check_grid(t_max, rz_max, rz_step)
    workers = workers or default_workers()
    if no_align and align_hint is not None:
        raise click.UsageError("--align-hint seeds the alignment that --no-align skips: "
                               "give one of them", ctx=ctx)
    six = _six_d_options(grid_kind, rz_max, dict(focal=focal, tz_max=tz_max, tz_step=tz_step,
                                                 tilt_max=tilt_max, tilt_step=tilt_step))
    plan = _plan(ctx, config, six, max_pixels, nodata, quiet, dict(
        t_max=t_max, rz_max=rz_max, rz_step=rz_step, lam=lam, tile_size=tile_size,
        threshold=threshold, workers=workers, scheduler=scheduler, illumination=illumination,
        shutter=shutter, align=not no_align, refine=not no_refine, local_field=not no_field,
        align_hint=align_hint, windows=windows, boxes=boxes, large_side=large_side))
    if _single_observation(observed):
        if every is not None or frames is not None:
            raise click.UsageError("--every and --frames pick the frames of a video; OBSERVED "
                                   "is one image", ctx=ctx)
        _detect_single(reference, observed[0], out, truth, plan, overwrite, t0)
        return
    if truth is not None:
        raise click.UsageError("--truth scores one observation: give one OBSERVED", ctx=ctx)
    sources = observation_sources(observed)
    if (every is not None or frames is not None) and not any(
            s.kind == "video" for s in sources):
        raise click.UsageError("--every and --frames pick the frames of a video; OBSERVED "
                               "names none", ctx=ctx)
    _detect_many(reference, observed, sources, out, plan, every or 1, frames or (0, None),
                 overwrite)


def _single_observation(observed: tuple[Path, ...]) -> bool:
    """One OBSERVED naming one image file (or zarr store): the single-pair layout."""
    from .many import VIDEO_SUFFIXES, _is_zarr

    if len(observed) != 1:
        return False
    p = observed[0]
    if p.is_dir():
        return _is_zarr(p)
    if not p.exists() and not p.is_symlink() and glob.has_magic(str(p)):
        return False
    return p.suffix.lower() not in VIDEO_SUFFIXES


@dataclasses.dataclass(frozen=True)
class _Plan:
    """What every observation of a run shares: :func:`reblur.detect_changes`' options,
    the configuration file, and the options settled per observation (the 6-D grid's
    focal length, the selection's window count)."""

    options: dict[str, Any]
    six: dict[str, Any] | None
    config: Any
    max_pixels: int
    nodata: float | None
    quiet: bool


def _plan(ctx: click.Context, config: Any, six: dict[str, Any] | None, max_pixels: int,
          nodata: float | None, quiet: bool, options: dict[str, Any]) -> _Plan:
    """The run's options: the flags, the --config file's tables where no flag was given
    explicitly (a flag given explicitly wins)."""
    def explicit(name: str) -> bool:
        src = ctx.get_parameter_source(name)
        return src is not None and src.name not in ("DEFAULT", "DEFAULT_MAP")

    if config.select is not None:
        for key in ("lam", "windows"):
            if config.sets("select", key) and not explicit(key):
                options[key] = getattr(config.select, key)
    options.update(decision=config.decision, rolling=config.rolling,
                   align_params=config.align)
    return _Plan(options, six, config, max_pixels, nodata, quiet)


def _options_for(plan: _Plan, observed: Path | None,
                 shape: tuple[int, int]) -> tuple[dict[str, Any], dict[str, Any]]:
    """:func:`reblur.detect_changes`' options for one observation of ``shape`` (``observed``:
    its file, for the focal length in its EXIF) and what to record about its grid."""
    from .pipeline import default_windows

    options = dict(plan.options)
    recorded: dict[str, Any] = dict(grid="3d")
    if plan.six is not None:
        gp, source = _grid_params(plan.six, observed, options["t_max"], options["rz_step"])
        options["grid"] = gp
        recorded = dict(grid="6d", grid_params=vars(gp).copy(), focal_source=source)
    if plan.config.select is not None:
        windows = options["windows"] or default_windows(shape, options["large_side"])
        options["select"] = dataclasses.replace(plan.config.select, lam=options["lam"],
                                                windows=windows)
    return options, recorded


def _recorded(options: dict[str, Any], plan: _Plan, **extra: Any) -> dict[str, Any]:
    """The options as report.json records them (dataclasses as their fields)."""
    rec = {k: (dataclasses.asdict(v) if dataclasses.is_dataclass(v) else v)
           for k, v in options.items() if k != "grid"}
    hint = options.get("align_hint")
    rec.update(align_hint=None if hint is None else np.asarray(hint).tolist(),
               max_pixels=plan.max_pixels, nodata=plan.nodata,
               config=plan.config.source)
    rec.update(extra)
    return rec


def _six_d_options(kind: str, rz_max: float, given: dict[str, Any]) -> dict[str, Any] | None:
    """The 6-D grid's options (None for --grid 3d); its flags without --grid 6d refused."""
    named = [f"--{k.replace('_', '-')}" for k, v in given.items() if v is not None]
    if kind == "3d":
        if named:
            raise click.UsageError(f"{', '.join(named)} apply to the 6-D grid: add --grid 6d")
        return None
    src = click.get_current_context().get_parameter_source("rz_max")
    explicit = src is not None and src.name != "DEFAULT"
    return dict({k: v for k, v in given.items() if v is not None},
                rz_max=rz_max if explicit else None)


def _grid_params(six: dict[str, Any], observed: Path | None, t_max: int,
                 rz_step: float | None):
    """The 6-D :class:`~reblur.grid.GridParams` (the focal length from --focal, else from
    OBSERVED's EXIF, else the default) and how the focal length was found."""
    from .grid import GridParams
    from .io import exif_focal_px

    six = dict(six)
    source = "--focal"
    if six.get("focal") is None:
        six["focal"] = exif_focal_px(observed) if observed is not None else None
        source = "EXIF FocalLengthIn35mmFilm" if six["focal"] is not None else "default"
    gp = GridParams(kind="6d", t_max=t_max, rz_step=rz_step, **six)
    return gp, source


def _detect_single(reference: Path, observed: Path, out: Path, truth: Path | None,
                   plan: _Plan, overwrite: bool, t0: float) -> None:
    """``reblur detect REF OBS``: one pair, its outputs directly in ``out``."""
    from .report import OUTPUT_NAMES, summary_line

    inputs = [reference, observed] + ([truth] if truth is not None else [])
    out_dir = _check_output_dir(out, inputs, OUTPUT_NAMES, overwrite)
    with output_set(out_dir, OUTPUT_NAMES, overwrite=overwrite, last=REPORT_NAMES,
                    manifest="report.json") as stage:
        ref, obs = _open_pair(reference, observed, plan.max_pixels, plan.nodata)
        truth_mask = (read_mask(truth, obs.shape[:2], max_pixels=plan.max_pixels,
                                what="truth mask") if truth is not None else None)
        t_open = time.perf_counter() - t0
        log.info("reference %s %s, observed %s %s", ref.shape, ref.dtype, obs.shape, obs.dtype)
        summary = _detect_one(stage, out_dir, ref, obs, observed, plan,
                              None if plan.quiet else _Progress(), truth=truth_mask,
                              timings=dict(open=t_open),
                              extra=dict(truth=str(truth) if truth is not None else None))
    click.echo(display_path(summary_line(summary, out)))


def _detect_one(stage: Path, out_dir: Path, ref: Image, obs: Image, observed: Path | None,
                plan: _Plan, progress: _Progress | None, *, truth=None,
                timings: dict[str, float] | None = None, extra: dict[str, Any] | None = None,
                reference_array: Any = None, cache: Any = None) -> dict[str, Any]:
    """Detect and write one observation's outputs into ``stage``, the temporary directory
    that becomes ``out_dir``; returns the content of its report.json.  ``reference_array``
    and ``cache``: the reference as detected and its :class:`reblur.ReferenceCache` (a
    run of several observations)."""
    import reblur

    from .report import write_report

    options, recorded = _options_for(plan, observed, obs.shape[:2])
    georef = None
    if options.get("align", True) and options.get("align_hint") is None:
        # two georeferenced inputs: their CRSs and transforms seed the alignment
        from .align.georef import image_prior

        prior = image_prior(ref, obs)
        if prior is not None:
            options = dict(options, align_hint=prior.H)
            georef = prior.to_dict()
            log.info("alignment seeded by the georeferencing (fit residual %.2f px)",
                     prior.residual_max)
    # full-size masks of large inputs (and every mask written by Dask workers) go to a zarr
    # store in the temporary output directory, never to memory; it is removed once the
    # outputs exist
    large = obs.n_pixels > LARGE_MASK_PIXELS
    work = (stage / f".reblur-work-{os.getpid()}"
            if options["scheduler"] is not None or large else None)
    try:
        from .gis import ReblurredStore

        masks = {}
        if large:
            masks = dict(zip(("change_out", "unknown_out"),
                             zarr_masks(work, obs.shape[:2], options["tile_size"]), strict=True))
            # the reblurred reference, too large to keep in memory, streamed to disk
            masks["reblurred_out"] = ReblurredStore(work / "reblurred", obs.shape, obs.dtype,
                                                    options["tile_size"])
        elif options["scheduler"] is None:
            # kept in memory in the observation's dtype, as reblurred.tif holds it (not as
            # float32: a quarter of the memory for 8-bit data)
            masks["reblurred_out"] = ReblurredStore(None, obs.shape, obs.dtype,
                                                    options["tile_size"])
        try:
            result = reblur.detect_changes(
                ref.for_detection() if reference_array is None else reference_array,
                obs.for_detection(), progress=progress, work_dir=work, **masks,
                **options, **({} if cache is None else dict(reference_cache=cache)))
            with _writing(out_dir):
                _, summary = write_report(
                    result, stage, reference=ref, observed=obs, truth=truth,
                    options=_recorded(options, plan, **recorded, command="detect",
                                      georef_prior=georef, **(extra or {})),
                    timings=timings, progress=progress,
                )
        finally:
            if progress is not None:
                progress.close()
    finally:
        if work is not None:
            shutil.rmtree(work, ignore_errors=True)
    return summary


#: Files of a run of several observations, besides the observations' folders.
MANY_NAMES = ("index.html", "summary.csv")


def _detect_many(reference: Path, observed: tuple[Path, ...], sources: list, out: Path,
                 plan: _Plan, every: int, frames: tuple[int, int | None],
                 overwrite: bool) -> None:
    """``reblur detect REF OBS [OBS ...]``: each observation into its folder OUT/NAME,
    the list of them into OUT/index.html and OUT/summary.csv."""
    from .many import iter_observations, summary_row, write_index_html, write_summary_csv
    from .refcache import ReferenceCache
    from .report import OUTPUT_NAMES

    inputs = [reference, *observed, *(s.path for s in sources)]
    out_dir = _check_output_dir(out, inputs, MANY_NAMES + OUTPUT_NAMES, overwrite,
                                sub_names=OUTPUT_NAMES)
    ref = open_image(reference, max_pixels=plan.max_pixels, nodata=plan.nodata)
    for note in ref.notes:
        log.info("%s: %s", ref.name, note)
    variants: dict[int, tuple[Image, Any, ReferenceCache]] = {}
    rows: list[dict[str, str]] = []

    def unreadable(src, exc: Exception) -> None:
        rows.append(summary_row(src.path.stem, str(src.path), reason=_describe(exc)))
        click.echo(display_path(f"{src.path.name}: failed: {rows[-1]['reason']}"))

    with output_set(out_dir, MANY_NAMES, overwrite=overwrite, last=("index.html",)) as top:
        for k, ob in enumerate(iter_observations(sources, every=every, frames=frames,
                                                 on_error=unreadable), 1):
            row = _one_of_many(k, ob, ref, variants, out_dir, plan, overwrite)
            rows.append(row)
            what = (f"{row['changed_percent']} % changed in {row['regions']} regions"
                    if row["status"] == "ok" else f"failed: {row['reason']}")
            click.echo(display_path(f"{ob.name}: {what} ({row['seconds']} s)"))
        if not rows:
            raise click.ClickException("no observation to compare: the videos hold no frame "
                                       "in the --frames range")
        totals: dict[str, Any] = {"reused": {}}
        for _, _, cache in variants.values():
            for kind, n in cache.totals()["reused"].items():
                totals["reused"][kind] = totals["reused"].get(kind, 0) + n
        with _writing(out_dir):
            write_summary_csv(top / "summary.csv", rows)
            write_index_html(top / "index.html", rows, reference=str(reference),
                             totals=totals)
    failed = sum(r["status"] != "ok" for r in rows)
    click.echo(display_path(f"{len(rows)} observations: {len(rows) - failed} ok, {failed} "
                            f"failed -> {out / 'index.html'}"))
    if failed:
        raise click.ClickException(f"{failed} of {len(rows)} observations failed (reasons in "
                                   f"{_show(out / 'summary.csv')})")


def _reference_variant(ref: Image, obs: Image, variants: dict) -> tuple[Image, Any, Any]:
    """The reference as compared with ``obs`` (in gray for a gray observation of an RGB
    reference), its detection array and its cache, made once per variant."""
    from .refcache import ReferenceCache

    key = 1 if (ref.bands == 3 and obs.bands == 1) else ref.bands
    if key not in variants:
        r = reconcile_bands(ref, obs)[0] if key != ref.bands else ref
        array = r.for_detection()
        variants[key] = (r, array, ReferenceCache(array))
    return variants[key]


def _one_of_many(k: int, ob: Any, ref: Image, variants: dict, out_dir: Path, plan: _Plan,
                 overwrite: bool) -> dict[str, str]:
    """Detect one observation of a run into ``out_dir/NAME``: its summary row, or the
    row of its failure (the run goes on)."""
    from .many import summary_row
    from .report import OUTPUT_NAMES

    t0 = time.perf_counter()
    progress = None if plan.quiet else _Progress(prefix=f"[{k}] {ob.name}: ")
    try:
        if ob.array is not None:  # a video frame
            obs = Image.from_array(ob.array, ob.label)
            if plan.nodata is not None:
                obs = obs.with_nodata(plan.nodata)
        else:
            obs = open_image(ob.path, max_pixels=plan.max_pixels, nodata=plan.nodata)
        check_sizes(ref, obs)
        ref_v, array, cache = _reference_variant(ref, obs, variants)
        _, obs = reconcile_bands(ref_v, obs)
        t_open = time.perf_counter() - t0
        with output_set(out_dir / ob.name, OUTPUT_NAMES, overwrite=overwrite,
                        last=REPORT_NAMES, manifest="report.json") as stage:
            summary = _detect_one(stage, out_dir / ob.name, ref_v, obs,
                                  ob.path if ob.frame is None else None, plan, progress,
                                  timings=dict(open=t_open), reference_array=array,
                                  cache=cache, extra=dict(observation=ob.label))
    except click.ClickException as exc:
        return summary_row(ob.name, ob.label, reason=exc.format_message(),
                           seconds=time.perf_counter() - t0)
    except Exception as exc:  # noqa: BLE001 - one observation fails, the run goes on
        if _STATE["verbose"]:
            traceback.print_exc()
        return summary_row(ob.name, ob.label, reason=_describe(exc),
                           seconds=time.perf_counter() - t0)
    finally:
        if progress is not None:
            progress.close()
    return summary_row(ob.name, ob.label, summary, seconds=time.perf_counter() - t0)


@main.command(short_help="Run detection on the embedded demo pair.")
@click.option("-o", "--out", type=_PATH, default=Path("reblur-demo"), show_default=True,
              help="Output directory.")
@overwrite_option
@quiet_option
@verbose_option
def demo(out: Path, overwrite: bool, quiet: bool) -> None:
    """Detect changes in the demo pair shipped with reblur and write the report.

    The pair is a real photograph, re-viewpointed, shaken and changed; its true change
    mask is known, so report.json also holds the scores.
    """
    from .data import demo_pair
    from .report import OUTPUT_NAMES, summary_line, write_report

    out_dir = _check_output_dir(out, [], OUTPUT_NAMES, overwrite)
    reference, observed, truth = demo_pair()
    ref = Image.from_array(reference, "demo reference")
    obs = Image.from_array(observed, "demo observed")
    import reblur

    with output_set(out_dir, OUTPUT_NAMES, overwrite=overwrite, last=REPORT_NAMES,
                    manifest="report.json") as stage:
        progress = None if quiet else _Progress()
        try:
            result = reblur.detect_changes(ref.for_detection(), obs.for_detection(),
                                           progress=progress)
            with _writing(out_dir):
                _, summary = write_report(result, stage, reference=ref, observed=obs,
                                          truth=truth, options=dict(command="demo"),
                                          progress=progress)
        finally:
            if progress is not None:
                progress.close()
    click.echo(display_path(summary_line(summary, out)))
    click.echo(f"open {_show(out / 'report.html')} for the full report")


@main.command(short_help="Make a synthetic blurred pair with known changes.")
@click.argument("image", type=_PATH)
@click.option("-o", "--out", type=_PATH, required=True, help="Output directory.")
@click.option("--after", type=_PATH, default=None,
              help="A real later image of the same scene (aligned with IMAGE) to blur.")
@click.option("--seed", type=int, default=0, show_default=True, help="Random seed.")
@click.option("--t-max", type=_Finite(min=0, max=1000), default=6.0, show_default=True,
              help="Camera shake: largest translation (pixels).")
@click.option("--rz-max", type=_Finite(min=0, max=45), default=1.0, show_default=True,
              help="Camera shake: largest in-plane rotation (degrees).")
@click.option("--shift-frac", type=_Finite(min=0, max=0.5), default=0.02, show_default=True,
              help="Viewpoint change: largest shift, as a fraction of the image size.")
@click.option("--rot-deg", type=_Finite(min=0, max=180), default=2.0, show_default=True,
              help="Viewpoint change: largest rotation (degrees).")
@click.option("--changes", "n_changes", type=click.IntRange(min=0), default=4,
              show_default=True, help="Number of pasted objects.")
@click.option("--moving/--no-moving", default=True, show_default=True,
              help="Add an object moving during the exposure.")
@click.option("--noise", type=_Finite(min=0, max=1), default=1.0 / 255.0,
              show_default="1/255", help="Gaussian noise sigma (intensities in [0, 1]).")
@max_pixels_option(100_000_000)
@overwrite_option
@verbose_option
def simulate(image: Path, out: Path, after: Path | None, seed: int, t_max: float,
             rz_max: float, shift_frac: float, rot_deg: float, n_changes: int, moving: bool,
             noise: float, max_pixels: int, overwrite: bool) -> None:
    """Simulate a test pair from IMAGE: a reference and a shaken, re-viewpointed observation
    of the changed scene, with the true changes.

    Writes reference.tif and observed.tif (float32 in [0, 1], so nothing is quantised
    away), truth.png and unknown.png (255/0, observation frame) and path.json (camera
    path, viewpoint homography, options).  Then try
    'reblur detect OUT/reference.tif OUT/observed.tif --truth OUT/truth.png --out RESULTS'.
    """
    import numpy as np

    inputs = [image] + ([after] if after is not None else [])
    out_dir = _check_output_dir(out, inputs, SIMULATE_NAMES, overwrite)
    with output_set(out_dir, SIMULATE_NAMES, overwrite=overwrite, last=("path.json",)) as stage:
        pair = _simulate(stage, out_dir, image, after, seed, t_max, rz_max, shift_frac,
                         rot_deg, n_changes, moving, noise, max_pixels)
    frac = float(np.mean(pair.truth))
    click.echo(f"simulated {pair.observed.shape[1]}x{pair.observed.shape[0]} pair, "
               f"{100 * frac:.2f} % changed -> {_show(out)}")


def _simulate(stage: Path, out_dir: Path, image: Path, after: Path | None, seed: int,
              t_max: float, rz_max: float, shift_frac: float, rot_deg: float, n_changes: int,
              moving: bool, noise: float, max_pixels: int):
    """The work of ``reblur simulate``: every file is written into ``stage``."""
    import numpy as np

    from .io import write_json, write_png, write_tiff
    from .simulate import make_pair

    before = open_image(image, max_pixels=max_pixels).read()
    later = open_image(after, max_pixels=max_pixels).read() if after is not None else None
    if later is not None and later.shape != before.shape:
        raise click.ClickException(f"{_show(after)}: shape {later.shape} differs from "
                                   f"{_show(image)}'s {before.shape}")
    pair = make_pair(
        before, later, rng=np.random.default_rng(seed),
        shake=dict(t_max=t_max, rz_max=rz_max) if (t_max or rz_max) else None,
        viewpoint=(dict(max_shift_frac=shift_frac, max_rot_deg=rot_deg)
                   if (shift_frac or rot_deg) else None),
        n_changes=n_changes, moving=moving, noise_sigma=noise,
    )
    meta = dict(pair.meta(), image=str(image), after=str(after) if after else None,
                options=dict(seed=seed, t_max=t_max, rz_max=rz_max, shift_frac=shift_frac,
                             rot_deg=rot_deg, changes=n_changes, moving=moving, noise=noise))
    with _writing(out_dir):
        write_tiff(stage / "reference.tif", np.asarray(pair.reference, np.float32))
        write_tiff(stage / "observed.tif", np.asarray(pair.observed, np.float32))
        write_png(stage / "truth.png", np.asarray(pair.truth, bool), flat=True)
        write_png(stage / "unknown.png", np.asarray(pair.unknown, bool), flat=True)
        write_json(stage / "path.json", meta)
    return pair


@main.command(short_help="Score a change mask against the truth (JSON on stdout).")
@click.argument("predicted", type=_PATH)
@click.argument("truth", type=_PATH)
@click.option("--unknown", type=_PATH, default=None,
              help="Mask of pixels to ignore (non-zero = ignore), e.g. unknown.png.")
@max_pixels_option(DEFAULT_MAX_PIXELS)
@verbose_option
def evaluate(predicted: Path, truth: Path, unknown: Path | None, max_pixels: int) -> None:
    """Compare the PREDICTED change mask with the TRUTH mask (non-zero = change).

    Prints JSON: pcc, jaccard, yule, precision, recall, f1 and the pixel counts
    (undefined scores are null).
    """
    from .io import to_jsonable
    from .metrics import change_metrics

    pred = read_mask(predicted, max_pixels=max_pixels, what="predicted mask")
    true = read_mask(truth, pred.shape, max_pixels=max_pixels, what="truth mask")
    ign = (read_mask(unknown, pred.shape, max_pixels=max_pixels, what="unknown mask")
           if unknown is not None else None)
    scores: dict[str, Any] = change_metrics(true, pred, ignore=ign)
    click.echo(json.dumps(to_jsonable(scores), indent=2, allow_nan=False))
