"""Object proposals (qBBs): the built-in proposers, the plug-in registry and the stage."""
