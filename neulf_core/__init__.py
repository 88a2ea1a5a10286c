"""neulf_core: neural 4D light fields (NeuLF) from forward-facing captures, Blender-free.

Data flows one way: scene -> rays -> slab -> dataset -> field -> trainer -> renderer.
"""

import sys

# Said before anything else is imported: an older Python (say, one chosen in Blender's
# preferences) would otherwise fail on the syntax of a module further in, naming neither.
if sys.version_info < (3, 10):
    sys.exit("error: neulf_core needs Python 3.10 or newer; this is Python %d.%d (in Blender: choose another Python in the NeuLF preferences)." % sys.version_info[:2])

__version__ = "0.1.0"
