"""The core's messages in Blender's words.

neulf_core says what to do in the command line's terms ("pass --images DIR", "train into
another --out folder"); in Blender the same choice is a field of a dialog or of the panel.
Each phrase below is one the core says where a Blender user can meet it (importing, loading,
training, rendering), with what the user does in Blender instead.  A message without one
passes unchanged."""

from __future__ import annotations

import re

# (a pattern of the core's words, the panel's); the more specific first.
_IMAGES = "choose {what} as Images in Import COLMAP / LLFF"
PHRASES = [
    (r"pass --images with the folder that holds (it|them)", _IMAGES.format(what="the folder that holds \\1")),
    (r"give --images the folder that holds the photos", _IMAGES.format(what="the folder that holds the photos")),
    (r"give --images with the folder it trained on", _IMAGES.format(what="the folder it trained on")),
    (r"pass --images DIR", _IMAGES.format(what="the photos' folder")),
    (r"To make one from photos run: python -m neulf_core reconstruct PHOTOS --out ('[^']*'|\S+)",
     "To make one from photos, use Reconstruct Photos in the NeuLF panel"),
    (r"with --images naming the folder it trained on",
     "with the folder it trained on as Images in Import COLMAP / LLFF"),
    (r"\(or train into another --out\)", "(or choose another Model folder in the NeuLF panel)"),
    (r"train into another --out folder", "choose another Model folder in the NeuLF panel"),
    (r"train a new model into another --out folder", "train a new model into another Model folder"),
    (r"Train it further: --resume with a larger --minutes", "Press Train to train it further (it adds its Minutes)"),
    (r"a larger --scale, or leave it out for the default", "a larger Image Scale, or 0 for the default"),
    (r"a larger --scale", "a larger Image Scale"),
    (r"a smaller --scale", "a smaller Image Scale"),
]


def panel_words(message: str) -> str:
    """`message` with the core's command-line advice said as what to do in Blender."""
    for pattern, words in PHRASES:
        message = re.sub(pattern, words, message)
    return message
