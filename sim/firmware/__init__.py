"""Real flight-controller firmware in the loop: build (:mod:`.build`), lockstep bridge
(:mod:`.bridge`), open-loop filter replay (:mod:`.replay`). The firmware is a separate GPL-3.0
process; the project's patch to it lives in ``betaflight/patch/`` with its notice."""
