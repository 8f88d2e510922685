"""What `cvqpg fit` and `cvqpg encode` fit, as their flags give it: an image with its depth map (a file, or one
estimated from the image), or a built-in scene, and the settings of the fit (`FitInputs`); turned into the
configuration and the `source` that a run records (`config_and_source`), then into the scene (`scene_and_depth`).
Every command's input paths are checked for a length the file system takes before any is looked up
(`long_input_path`)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from ..config import FitConfig, RunOptions
from ..defaults import DEPTH_MODEL
from ..errors import UsageError

if TYPE_CHECKING:
    from PIL import Image

    from ..targets import Scene


def long_input_path(paths: dict[str, list[str]]) -> str | None:
    """The first of a command's input `paths` (by the flag or name that gave them) longer than the file system
    takes (`files.name_too_long`; looked up, it is an `OSError` of its own), as one line; None where none is."""
    from ..files import name_too_long
    for flag, values in paths.items():
        for value in values:
            if (problem := name_too_long(value)) is not None:
                return f"{flag} {value[:40]}…: {problem}; give a shorter path"
    return None


@dataclass(frozen=True)
class FitInputs:
    """A fit as the command line asks for it: `image` (a path) or the built-in `scene` (neither: `demo`), its
    `depth` (a path, `auto`, or None), `resize_depth` (a depth map of another aspect is stretched), the `recipe`
    (None: `FitConfig.create`'s, by the primitive) and `FitConfig.create`'s `settings` (`color`, `num_planes` and `steps` None where not given: the input decides
    them), and where it runs (`device`, `backend`)."""

    image: str | None
    scene: str | None
    depth: str | None
    resize_depth: bool
    recipe: str | None
    settings: dict[str, Any]
    device: str
    backend: str

    def run_options(self) -> RunOptions:
        return RunOptions(self.device, self.backend).validate()


def config_and_source(inputs: FitInputs) -> tuple[FitConfig, dict[str, Any]]:
    """The configuration of the fit `inputs` ask for, validated, and its `source` (what a run records of its
    inputs); a `UsageError` for inputs that do not go together."""
    from ..scenes import SCENES
    from ..targets import check_file
    if inputs.image is not None and inputs.scene is not None:
        raise UsageError("give either an IMAGE or --scene, not both")
    settings = inputs.settings
    if inputs.image is None:
        name = inputs.scene or "demo"
        if inputs.depth is not None:
            raise UsageError(f"--depth applies to an IMAGE; the built-in scene {name!r} has its own")
        recipe = SCENES[name]
        color = settings["color"] or recipe.color
        planes = recipe.planes if settings["num_planes"] is None else settings["num_planes"]
        source, has_depth = {"scene": name}, recipe.planes > 1
    else:
        color = settings["color"] or "rgb"
        planes = 2 if settings["num_planes"] is None else settings["num_planes"]
        source = {"image": str(check_file(inputs.image, "image").resolve())}
        if inputs.depth == "auto":
            source["depth_model"] = DEPTH_MODEL
        elif inputs.depth is not None:
            source["depth"] = str(check_file(inputs.depth, "depth map").resolve())
        has_depth = inputs.depth is not None
    if planes > 1 and not has_depth:
        raise UsageError(f"--planes {planes} needs a depth map (--depth PATH, or --depth auto to estimate one), "
                         "or use --planes 1")
    if inputs.resize_depth:
        source["resize_depth"] = True
    steps = FitConfig.create().optimisation.steps if settings["steps"] is None else settings["steps"]
    config = FitConfig.create(inputs.recipe, **{**settings, "color": color, "num_planes": planes, "steps": steps})
    return config.validate(), source


def scene_and_depth(source: dict[str, Any], config: FitConfig) -> tuple[Scene, Image.Image | None]:
    """The scene of `config_and_source`'s `source`, and the depth map estimated for it (`--depth auto`)."""
    from ..depth import estimate_depth, load_depth_model
    from ..runs import scene_from_source
    from ..targets import load_scene
    if "depth_model" not in source:
        return scene_from_source(source, config), None
    depth = estimate_depth(source["image"], load_depth_model(source["depth_model"]))
    return load_scene(source["image"], depth, config), depth


def source_files(source: dict[str, Any]) -> list[Path]:
    """The input files a run's `source` names, which no output may replace."""
    return [Path(source[key]) for key in ("image", "depth") if key in source]
