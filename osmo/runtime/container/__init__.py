"""The container runtime family: a task with an ``image:`` runs in that image.

Modules: ``runtime`` (:class:`ContainerRuntime`, the runtime: how a container task starts,
from its image to its clean-up), ``engine`` (the one module that runs a container engine's
CLI: images, networks, clean-up by label), ``run`` (a run's description and its argv,
pure), ``runs`` (a run's life through the engine's attached CLI), ``pull`` (a pull with
registry credentials), ``images`` (image ids per workflow, registry credentials),
``layout`` (OSMO's data layout inside the container, pure), ``groups`` (group networks and
the lead's start).
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
from osmo.runtime.container.runs import ContainerRuns
from osmo.runtime.container.runtime import ContainerRuntime, owner_id

__all__ = ["DATA_OUTPUT", "ENGINES", "SECRET_ENV_PATH", "ContainerEngine", "ContainerError",
           "ContainerRun", "ContainerRuns", "ContainerRuntime", "EngineInfo", "EngineNotFound",
           "ImageError", "ImageInfo", "Mount", "RegistryAuth", "data_input", "detect_engine",
           "owner_id", "run_argv", "safe_name"]
