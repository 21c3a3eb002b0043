"""The build reads pyproject.toml ([project], [tool.setuptools]); this file is kept for the layout's sake."""

from setuptools import setup

setup()
