"""Recipes: loading, validation against a profile, and recipe text."""
