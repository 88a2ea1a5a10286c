"""neulf_core: neural 4D light fields (NeuLF) from forward-facing captures, Blender-free.

Data flows one way: scene -> slab -> rays -> field -> trainer -> renderer.
"""

__version__ = "0.1.0"
