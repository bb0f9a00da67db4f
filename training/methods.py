"""The training methods by name: the one list ``bioscara train``, its ``--algo`` and model loading read.

As rl-zoo3 keeps ``ALGOS`` and Gymnasium its registrations: one
:class:`MethodSpec` per method, names and entry-point strings only, so the
CLI lists the choices without importing torch. A method is a
:class:`~bioscara_gym.training.base.TrainingMethod` subclass (the steps of
one run, see :mod:`~bioscara_gym.training.base`) in a module of its own;
adding one is that module and one :func:`register_method` line below.
Nothing else branches on a method's name: ``--algo`` takes the keys of
:data:`METHODS`, :data:`~bioscara_gym.training.algos.ALGOS` and
:data:`~bioscara_gym.training.algos.MODEL_CLASSES` are derived from it, and
a task without ``--algo`` trains with its own ``default_method``
(:data:`bioscara_gym.tasks.TASKS`).
"""

from __future__ import annotations

from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import Any

from bioscara_gym.errors import TrainingError
from bioscara_gym.tasks import TASKS, load_entry_point

#: The runner of the stable-baselines3 algorithms rl-zoo3 also trains.
SB3_RUNNER = "bioscara_gym.training.sb3:SB3Method"


@dataclass(frozen=True)
class MethodSpec:
    """One training method, by name.

    Attributes:
        name: The ``--algo`` name.
        entry_point: Its :class:`~bioscara_gym.training.base.TrainingMethod`, ``module:Class``.
        help: A few words for ``bioscara train --help``.
        model: The stable-baselines3 class its ``model.zip`` is (and loads as).
        saves_as: The ``algo`` its metadata states (what ``eval``, ``export``
            and ``deploy`` load the model as); default :attr:`name`. A method
            saving as another's records its own name as ``method``.
        config: The packaged hyperparameter file (``training/configs/``).
        config_loader: Reads one env's entry of such a file, ``module:function``
            (``path, env_id`` -> a config with ``env_kwargs``).
    """

    name: str
    entry_point: str
    help: str
    model: str
    saves_as: str = ""
    config: str = ""
    config_loader: str = "bioscara_gym.training.hyperparams:load_hyperparams"

    @property
    def algo(self) -> str:
        """The ``algo`` the saved model's metadata states."""
        return self.saves_as or self.name

    @property
    def rl_zoo(self) -> bool:
        """Whether it is a stable-baselines3 algorithm trained from an rl-zoo3 file of its own name."""
        return self.entry_point == SB3_RUNNER

    def default_config(self) -> Path:
        """The packaged hyperparameter file."""
        return Path(str(resources.files("bioscara_gym.training") / "configs" / self.config))

    def load_config(self, path: Path, env_id: str) -> Any:
        """``env_id``'s entry of hyperparameter file ``path``, checked.

        Raises:
            HyperparamError: See the loader.
        """
        return load_entry_point(self.config_loader)(path, env_id)

    def method_class(self) -> type:
        """The :class:`~bioscara_gym.training.base.TrainingMethod` (its module is imported: torch)."""
        return load_entry_point(self.entry_point)


#: Every method, in the order ``--algo`` lists them.
METHODS: dict[str, MethodSpec] = {}


def register_method(spec: MethodSpec) -> None:
    """Add ``spec`` to :data:`METHODS` (its default config: ``NAME.yaml``)."""
    if not spec.config:
        spec = MethodSpec(**{**spec.__dict__, "config": f"{spec.name}.yaml"})
    METHODS[spec.name] = spec


register_method(MethodSpec("sac", SB3_RUNNER, "SAC (+HER on the goal tasks)", model="SAC"))
register_method(MethodSpec("td3", SB3_RUNNER, "TD3 (+HER on the goal tasks)", model="TD3"))
register_method(MethodSpec("ppo", SB3_RUNNER, "PPO", model="PPO"))
register_method(
    MethodSpec(
        "bc", "bioscara_gym.training.bc:BehaviourCloning", "behaviour cloning", model="SAC", config="sac.yaml"
    )
)
register_method(
    MethodSpec(
        "dagger",
        "bioscara_gym.training.dagger:DAgger",
        "DAgger",
        model="SAC",
        saves_as="bc",
        config_loader="bioscara_gym.training.dagger_config:load_dagger_config",
    )
)


def method_spec(name: str) -> MethodSpec:
    """The method called ``name``.

    Raises:
        TrainingError: No such method; the message lists them.
    """
    if name not in METHODS:
        raise TrainingError(f"unknown algo {name!r}; choose one of {', '.join(METHODS)}")
    return METHODS[name]


def default_env_kwargs(env_id: str) -> dict[str, Any]:
    """The ``env_kwargs`` of the packaged config of ``env_id``'s default method (PickPlace: DAgger's).

    Raises:
        HyperparamError: The packaged file has no entry for ``env_id``, or a malformed one.
    """
    spec = METHODS[TASKS[env_id].default_method if env_id in TASKS else "sac"]
    return dict(spec.load_config(spec.default_config(), env_id).env_kwargs)
