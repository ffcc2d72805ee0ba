"""Data sources, chosen by name from an explicit registry."""

from frontends.sources.base import SOURCES, Source, make_source, register_source

__all__ = ["SOURCES", "Source", "make_source", "register_source"]
