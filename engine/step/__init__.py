"""The time step as the paper's pipeline, and the run: Δt control and the step's checks
(:mod:`.stepping`), the update after a converged step (:mod:`.advance`), the energy watchdog
(:mod:`.energy`), what a recorder receives (:mod:`.frame`, :mod:`.output`) and the
orchestrator (:mod:`.simulation`: a step is named stages; checkpoints and resume).

May import :mod:`engine.contact` and everything below it.
"""
