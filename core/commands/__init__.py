"""Command modules of the ``inspect`` CLI; each exposes ``register(cli)``."""
