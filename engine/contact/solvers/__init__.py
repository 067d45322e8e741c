"""The contact solvers: how a step's contacts are solved, behind one call.

Each solver takes the step's block system, its state, its contacts and their bonded patches
and returns a :class:`engine.contact.solution.StepResult` (or raises StepFailure, and the
step is redone with a smaller Δt). :mod:`.dispatch` chooses by `analysis.contact_solver`:
the paper's open-close iteration on penalty springs (:mod:`.open_close`, :mod:`.damping`)
and the complementarity solve without springs (:mod:`.complementarity`,
:mod:`.active_set`). The solvers import the rest of `engine.contact` (constraints,
patches), `engine.dynamics` and below; nothing in `engine.contact` outside this room
imports a solver.
"""

from engine.contact.solvers.dispatch import settle_contacts, solve_contacts

__all__ = ["settle_contacts", "solve_contacts"]
