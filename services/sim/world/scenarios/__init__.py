"""Shipped scenario files (YAML); a package so the wheel includes them as package data."""
