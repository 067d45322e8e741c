"""Contacts: the generalized contact constraints of the paper (two points, one plane, a
mode; :mod:`.constraints`), their detection (broad and narrow phase, :mod:`.detection`),
the contacts of a step (search reach, materials; :mod:`.search`), their face-to-face
patches that carry a joint's cohesion and tension as one bond (:mod:`.patches`), and the
contact solution of a step: the paper's open-close iteration (:mod:`.open_close`, Tables 1
and 2) and the damping of rings and rebounds (:mod:`.damping`), both returning a
:class:`.solution.StepResult`.

May import :mod:`engine.dynamics` and everything below it; never :mod:`engine.step` or
above.
"""
