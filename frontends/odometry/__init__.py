"""Odometry front-ends, chosen by name from an explicit registry."""

from frontends.odometry.base import ODOMETRIES, Odometry, make_odometry, register_odometry

__all__ = ["ODOMETRIES", "Odometry", "make_odometry", "register_odometry"]
