"""bioscara-gym: the Bioscara SCARA arm as a reinforcement-learning testbed.

``import bioscara_gym`` registers the Gymnasium tasks by entry-point string
(as ``gymnasium/envs/__init__.py`` does), so nothing else is imported: the
driver layer, :mod:`bioscara_gym.hardware`, works without Gymnasium, MuJoCo
or torch installed.

=========================  =============================================  =================
id                         entry point                                    max_episode_steps
=========================  =============================================  =================
``Bioscara-Reach-v0``      ``bioscara_gym.envs.reach:BioscaraReachEnv``   50 (2 s)
``Bioscara-PickPlace-v0``  ``bioscara_gym.envs.pick_place:...``           200 (8 s)
=========================  =============================================  =================

``gym.make("Bioscara-Reach")`` (no version) also works: Gymnasium picks the
latest version and says so in a warning, which this package does not hide
(importing it installs no warning filters).
"""

from __future__ import annotations

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("bioscara-gym")
except PackageNotFoundError:  # pragma: no cover - running from a source tree
    __version__ = "0.0.0+unknown"

#: Task id to (entry point, episode length in control steps).
TASKS = {
    "Bioscara-Reach-v0": ("bioscara_gym.envs.reach:BioscaraReachEnv", 50),
    "Bioscara-PickPlace-v0": ("bioscara_gym.envs.pick_place:BioscaraPickPlaceEnv", 200),
}


def register_envs() -> None:
    """Register the tasks with Gymnasium (idempotent; nothing happens without Gymnasium)."""
    try:
        import gymnasium
    except ModuleNotFoundError:
        return  # the driver layer alone (e.g. a robot computer without the envs)
    for env_id, (entry_point, steps) in TASKS.items():
        if env_id not in gymnasium.registry:
            gymnasium.register(id=env_id, entry_point=entry_point, max_episode_steps=steps)


register_envs()

__all__ = ["TASKS", "__version__", "register_envs"]
