"""Every exception meshmei raises for bad input: each a ``ValueError`` whose message names what arrived."""

__all__ = ["MeshError", "RenderError", "EncoderError", "MEIError", "ReconstructionError", "TuningError"]


class MeshError(ValueError):
    """A mesh (vertex or face array) is malformed; the message names the problem and what arrived."""


class RenderError(ValueError):
    """Bad input to the renderer (settings, camera, pose, light); the message names the value and what arrived."""


class EncoderError(ValueError):
    """Bad input to an encoder (image shape, neuron index, parameters); the message names what arrived."""


class MEIError(ValueError):
    """Bad input to the 3D-MEI optimisation or a bad run directory; the message names what arrived."""


class ReconstructionError(ValueError):
    """Bad reconstruction settings or schedule; the message names the setting and what arrived."""


class TuningError(ValueError):
    """Bad input to a sweep (ranges, neurons, run or sweep directories); the message says what arrived."""
