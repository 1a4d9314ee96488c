"""Flight-controller side: vibration analysis, the firmware filter chain and its preview."""
