"""The operator console: ``bioscara status``, ``enable``, ``home``, ``move``, ``monitor``, ``emulate``.

Modules, each importing only those above it:

- :mod:`~bioscara_gym.console.format`: units, numbers and flags as printed.
- :mod:`~bioscara_gym.console.targets`: the common options, joint and group names.
- :mod:`~bioscara_gym.console.state`: the ``--state`` file.
- :mod:`~bioscara_gym.console.session`: :class:`~bioscara_gym.console.session.Session`,
  one command's hold on backend, arm and state file.
- :mod:`~bioscara_gym.console.dashboard`: the live ``monitor``.
- :mod:`~bioscara_gym.console.commands`: the subcommands and ``register``.
- :mod:`~bioscara_gym.console.emulate`: ``bioscara emulate dynamixel``, emulated servos on a pty.
"""
