"""The measurement model: the effect registry (catalogue effects, noise terms, open families)."""
