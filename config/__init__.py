"""Configuration schema and loading for W-ARa tunnel projects."""

from config.loader import ConfigError, default_project_path, load_model, load_project
from config.schema import ProjectConfig

__all__ = ["ConfigError", "ProjectConfig", "default_project_path", "load_model", "load_project"]
