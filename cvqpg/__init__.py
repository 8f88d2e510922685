"""cvqpg: holograms as complex-valued (quadratic-phase) Gaussian primitives."""

__version__ = "0.1.0"

from .config import FitConfig, LearningRates
from .depth import estimate_depth, load_depth_model
from .fitting import FitResult, fit, fit_scene, render, render_hologram
from .metrics import MetricReport, evaluate
from .optics import Grid, propagate, reconstruct, transfer_function
from .primitives import Gaussians, Primitives, activate, init_gaussians
from .ops.rasterize import rasterize
from .runs import evaluate_run, write_run
from .scenes import builtin_scene
from .storage import load_model, save_model
from .targets import Scene, build_scene, load_scene

__all__ = [
    "FitConfig", "LearningRates", "FitResult", "fit", "fit_scene", "render", "render_hologram",
    "MetricReport", "evaluate", "Grid", "propagate", "reconstruct", "transfer_function",
    "Gaussians", "Primitives", "activate", "init_gaussians", "rasterize", "builtin_scene",
    "Scene", "build_scene", "load_scene", "evaluate_run", "write_run", "load_model", "save_model",
    "estimate_depth", "load_depth_model", "__version__",
]
