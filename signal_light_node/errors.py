"""Exception types of signal_light_node; every error the package raises on purpose is one of these."""


class SignalLightError(Exception):
    """Base class of all signal_light_node errors."""


class BagIOError(SignalLightError):
    """A bag or a message in it cannot be read, converted or written."""


class CropError(SignalLightError):
    """A box cannot be turned into a model crop (zero size, outside the image, not finite)."""


class CheckpointError(SignalLightError):
    """A model checkpoint is missing, unreadable or incompatible with this code."""


class ConfigError(SignalLightError):
    """A parameter or option has a value that cannot be used; the message says why."""


class ImageConversionError(BagIOError):
    """An image message cannot be turned into a BGR array (or back); the message names topic and stamp."""


class ImageTooLargeError(ImageConversionError):
    """An image exceeds the configured pixel limit; refused before it is decoded."""


class AnnotationError(SignalLightError):
    """A labelling file does not fit the bag or the export it is checked against, or cannot
    be read; the message names the first mismatch in one line."""
