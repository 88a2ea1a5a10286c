"""User-facing errors.

Anything a user can cause (a bad folder, a broken model, odd images, a camera the light
field cannot see from) raises :class:`NeulfError` with a message that says what happened
and what to do.  The CLI prints it as one line and exits non-zero; the Blender layer
shows it in the status bar.  Programming errors stay ordinary exceptions.
"""


class NeulfError(Exception):
    """An error caused by input the user can fix; the message says how."""
