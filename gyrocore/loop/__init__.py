"""The residual loop: residual against a reference, the open search, the add-and-refit loop."""
