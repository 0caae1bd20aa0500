"""Multi-view shape completion: grids, simulated data, models, streaming, meshes.

``completion.load_model(name)`` loads shipped weights (imported lazily, so that the numpy-only
modules such as ``completion.grid`` never pull in torch).
"""


def __getattr__(name: str):
    if name == "load_model":
        from completion.model import load_model

        return load_model
    raise AttributeError(f"module 'completion' has no attribute {name!r}")
