"""Reference derivations that share nothing with the natural-coordinate model."""
