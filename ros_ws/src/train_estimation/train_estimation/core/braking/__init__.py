"""Braking family of the estimation core (docs/nodes.md)."""
