"""Placeholder: filled in by the work on its issue."""
import click


def register(cli: click.Group) -> None:
    return None
