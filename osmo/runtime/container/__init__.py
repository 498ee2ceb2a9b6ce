"""The container runtime family: a task with an ``image:`` runs in that image.

Modules: ``engine`` (the one module that runs a container engine's CLI: images, networks,
clean-up by label), ``run`` (a run's description and its argv, pure), ``pull`` (a pull with
registry credentials), ``runs`` (a run's life through the engine's attached CLI).
"""

from osmo.runtime.container.engine import (
    ENGINES,
    ContainerEngine,
    EngineNotFound,
    ImageInfo,
    detect_engine,
)
from osmo.runtime.container.pull import ImageError
from osmo.runtime.container.run import (
    DATA_OUTPUT,
    SECRET_ENV_PATH,
    ContainerError,
    ContainerRun,
    EngineInfo,
    Mount,
    RegistryAuth,
    data_input,
    run_argv,
    safe_name,
)

__all__ = ["DATA_OUTPUT", "ENGINES", "SECRET_ENV_PATH", "ContainerEngine", "ContainerError",
           "ContainerRun", "EngineInfo", "EngineNotFound", "ImageError", "ImageInfo", "Mount",
           "RegistryAuth", "data_input", "detect_engine", "run_argv", "safe_name"]
