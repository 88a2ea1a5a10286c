"""User-facing errors.

Anything a user can cause (a bad folder, a broken model, odd images, a camera the light
field cannot see from) raises :class:`NeulfError` with a message that says what happened
and what to do.  The CLI prints it as one line and exits non-zero; the Blender layer
shows it in the status bar.  Programming errors stay ordinary exceptions.
"""


class NeulfError(Exception):
    """An error caused by input the user can fix; the message says how."""


# What a user sees where an exception that is not a NeulfError still has a cause they can act
# on: the worker, the CLI and Blender's in-process core all say it in these words.
OUT_OF_MEMORY = ("out of memory: render a smaller image, or train at a smaller --scale (in Blender a smaller Chunk "
                 "setting also lowers a render's peak).")
OTHER_PYTHONS_PACKAGES = ("the NeuLF Python's packages were built for another Python version (their compiled parts "
                          "do not load): click Install dependencies again in the NeuLF preferences, or choose the "
                          "Python they were installed with.")
# Compiled parts that fail to import when a package was installed for another Python version.
COMPILED_PARTS = ("_multiarray_umath", "torch._C", "pycolmap._core", "PIL._imaging", "av._core")


def missing_module_message(module: str) -> str:
    """What to do about a package the NeuLF Python lacks (or cannot load)."""
    if any(part in module for part in COMPILED_PARTS):
        return OTHER_PYTHONS_PACKAGES
    return (f"the NeuLF Python has no '{module}': set a Python with torch, numpy, pycolmap, Pillow and av (PyAV) in the "
            "NeuLF preferences, or click Install dependencies there.")


# The RuntimeErrors' words where torch's CPU and MPS allocators refuse: the CPU's "can't allocate
# memory", MPS's "MPS backend out of memory", and MPS's "Invalid buffer size: 74.51 GB" for one
# buffer larger than Metal allows (aten/src/ATen/mps/MPSAllocator.mm) -- a smaller chunk fits there too.
OUT_OF_MEMORY_WORDS = ("can't allocate memory", "out of memory", "Invalid buffer size: ")


def is_out_of_memory(exc: BaseException) -> bool:
    """Whether `exc` is a device running out of memory: Python's MemoryError, torch's
    OutOfMemoryError (CUDA), or the RuntimeError torch raises for the CPU and MPS allocators
    (they have no class of their own)."""
    if isinstance(exc, MemoryError) or type(exc).__name__ == "OutOfMemoryError":
        return True
    text = str(exc)
    return isinstance(exc, RuntimeError) and any(words in text for words in OUT_OF_MEMORY_WORDS)


def as_user_error(exc: BaseException) -> NeulfError | None:
    """The NeulfError for an exception whose cause a user can act on (memory, a missing or
    mismatched package), or None for a programming error."""
    if is_out_of_memory(exc):
        return NeulfError(OUT_OF_MEMORY)
    if isinstance(exc, ImportError):
        return NeulfError(missing_module_message(exc.name or str(exc)))
    return None
