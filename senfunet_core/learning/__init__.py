"""Offline tooling around the engine: simulated scenes and sensors, training, evaluation.

Nothing at run time imports this package: the node and replay need only the engine modules
one level up.
"""
