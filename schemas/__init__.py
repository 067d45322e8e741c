"""Scene schema (pydantic), validation errors and conversion of a scene to engine inputs."""

from schemas.convert import BuildResult, build_model
from schemas.errors import SceneError
from schemas.scene import SCHEMA_VERSION, Limits, Scene, load_scene, scene_json_schema

__all__ = [
    "SCHEMA_VERSION",
    "BuildResult",
    "Limits",
    "Scene",
    "SceneError",
    "build_model",
    "load_scene",
    "scene_json_schema",
]
