"""The operator console: ``bioscara status``, ``ping``, ``enable``, ``home``, ``move``, ``monitor``."""
