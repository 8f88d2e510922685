"""The one error family of the library: every problem a user can fix is a `CvqpgError`.

Messages name the parameter at fault in backticks, as the library spells it (`num_planes`,
`pixel_pitch`); the command line shows the same message with its own flag names (`--planes`,
`--pitch`). Anything else that escapes is a bug.
"""

from __future__ import annotations


class CvqpgError(Exception):
    """A problem with what the caller gave: a setting, an input file, a model or a folder."""


class ConfigError(CvqpgError, ValueError):
    """A setting that cannot work."""


class InputError(CvqpgError, ValueError):
    """An input image, depth map, scene or folder that cannot be used as given."""


class ModelFileError(CvqpgError, ValueError):
    """A model file or checkpoint that this version cannot read, or that does not belong where it is."""


def choices_error(name: str, value: object, choices: tuple[str, ...]) -> ConfigError:
    """The error for an enumerated setting given a value outside its choices."""
    return ConfigError(f"`{name}` {value!r} is not one of {', '.join(map(repr, choices))}")
