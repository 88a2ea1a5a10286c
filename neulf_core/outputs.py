"""Where `render --views` and `eval` write a view's images: one file name per view, and never
over the scene's own photos.

A rig's photos share their stems (left/f1.png, right/f1.png): named by stem alone, the second
view's render had replaced the first's without a word.  And `--out` naming the photos' own
folder had replaced the photos with renders, after which eval scored the renders against
themselves.  Both are decided here, before anything renders, for render and eval alike.
"""

from __future__ import annotations

import os
from collections import Counter
from pathlib import Path

from .errors import NeulfError


def view_file_stems(views, scene_views) -> dict[str, str]:
    """Each of `views`' file stem, by view name: its photo's stem (view_03 for view_03.png), or,
    where two of the scene's photos share a stem (a rig's left/f1.png and right/f1.png), its
    name's folders and stem joined by '_' (left_f1), for every view of the scene alike.  Decided
    over all of `scene_views`, so a view gets the same name whichever views are rendered with it."""
    stems = Counter(view.stem.lower() for view in scene_views)  # (lower: macOS and Windows fold case)
    if all(count == 1 for count in stems.values()):
        return {view.name: view.stem for view in views}
    return {view.name: "_".join(Path(view.name).with_suffix("").parts) for view in views}


def refuse_clashing_names(files_by_view: dict[str, list[str]], out: Path) -> None:
    """Refuse where two views would write the same file of `out` (names folding case, as macOS
    and Windows do): the second would silently replace the first."""
    owner: dict[str, str] = {}
    for view, files in files_by_view.items():
        for name in files:
            other = owner.setdefault(name.lower(), view)
            if other != view:
                raise NeulfError(f"the views {other} and {view} would both be written to {out / name}: rename one of "
                                 "their photos (and its name in the model), or render them one at a time into "
                                 "different folders.")


def photo_folders_of(scene_root) -> set[Path]:
    """A scene's photo folders besides the one read: `images/` and LLFF's `images_N/` copies (a
    model trained on images_8 had rendered over images_16's photos)."""
    root = Path(scene_root).expanduser()
    if not root.is_dir():
        return set()
    return {child for child in root.iterdir() if child.is_dir() and (child.name == "images"
                                                                     or child.name.startswith("images_"))}


def refuse_writing_over_photos(out: Path, file_names, photos, photo_folder=None, scene_root=None) -> None:
    """Refuse, before anything renders, an `out` that is a folder holding the scene's photos
    (`photo_folder`, the folder of any of `photos`, or a photo folder of `scene_root`), or where
    one of `file_names` is one of `photos` (the same file, however reached: a link, another
    letter case)."""
    out = Path(out).expanduser()
    photos = [Path(p) for p in photos if p is not None]
    folders = {Path(photo_folder)} if photo_folder is not None else set()
    folders |= {photo.parent for photo in photos}
    if scene_root is not None:
        folders |= photo_folders_of(scene_root)
    for folder in folders:
        if _same_file(out, folder):
            raise NeulfError(f"--out {out} is a folder of the scene's photos ({folder}): renders written there would "
                             "replace or mix with the photos; give --out another folder.")
    taken = {_identity(photo) for photo in photos} - {None}
    for name in file_names:
        if _identity(out / name) in taken:
            raise NeulfError(f"--out {out}: {out / name} is one of the scene's photos, which the render would replace; "
                             "give --out another folder.")


def _identity(path: Path):
    """(device, inode) of an existing file, else None."""
    try:
        status = os.stat(path)
    except OSError:
        return None
    return status.st_dev, status.st_ino


def _same_file(a: Path, b: Path) -> bool:
    try:
        return os.path.samefile(a, b)
    except OSError:
        return False
