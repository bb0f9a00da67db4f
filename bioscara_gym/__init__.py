"""bioscara-gym: the Bioscara SCARA arm as a reinforcement-learning testbed.

``import bioscara_gym`` registers the Gymnasium tasks of
:data:`~bioscara_gym.tasks.TASKS` by entry-point string (as
``gymnasium/envs/__init__.py`` does), so nothing else is imported: the
driver layer, :mod:`bioscara_gym.hardware`, works without Gymnasium, MuJoCo
or torch installed.

=========================  ==============================================  ==========
``gym.make("Bioscara-Reach")`` (no version) makes the latest version. Gymnasium
announces that choice with a warning on every make and refuses to register
an unversioned id beside a versioned one, so registration also installs one
warnings filter, scoped to that message, for this package's ids only, raised
from Gymnasium's registry (:data:`UNVERSIONED_MESSAGE`); any other warning,
and the same one for anyone else's env, is shown as before.
"""

from __future__ import annotations

import re
import warnings
from importlib.metadata import PackageNotFoundError, version

from bioscara_gym.tasks import TASKS

try:
    __version__ = version("bioscara-gym")
except PackageNotFoundError:  # pragma: no cover - running from a source tree
    __version__ = "0.0.0+unknown"

#: Gymnasium's warning when an unversioned id of ours picks the latest version, as a
#: regular expression (it colours the text, hence the leading ``.*``).
UNVERSIONED_MESSAGE = (
    r".*Using the latest versioned environment `(?:{ids})-v\d+` instead of the unversioned "
    r"environment `(?:{ids})`"
).format(ids="|".join(re.escape(env_id.rpartition("-v")[0]) for env_id in TASKS))


def register_envs() -> None:
    """Register the tasks with Gymnasium (idempotent; nothing happens without Gymnasium).

    Also installs the one filter that lets ``gym.make("Bioscara-Reach")`` pass
    without Gymnasium's unversioned-id warning (see the module docstring).
    """
    try:
        import gymnasium
    except ModuleNotFoundError:
        return  # the driver layer alone (e.g. a robot computer without the envs)
    for env_id, spec in TASKS.items():
        if env_id not in gymnasium.registry:
            gymnasium.register(
                id=env_id,
                entry_point=spec.entry_point,
                max_episode_steps=spec.max_episode_steps,
                kwargs=dict(spec.kwargs),
            )
    # filterwarnings drops an identical filter before inserting it: calling this again adds none.
    warnings.filterwarnings(
        "ignore", message=UNVERSIONED_MESSAGE, category=UserWarning, module=r"gymnasium\.envs\.registration"
    )


register_envs()

__all__ = ["TASKS", "UNVERSIONED_MESSAGE", "__version__", "register_envs"]
