"""Jobs: the SQLite job table (:mod:`.store`), the backends that run jobs (:mod:`.backend`
and its :mod:`.embedded` processes or :mod:`.rq` queue with :mod:`.rq_worker` /
:mod:`.worker`), the process registry (:mod:`.processes`) and the job function
(:mod:`.execute`, what a running job sees: :mod:`.tasks`), sweeps fanned out over the queue
(:mod:`.fanout`) and the data directory's lock (:mod:`.datadir`).

May import :mod:`service.sweep`, :mod:`service.documents` and :mod:`service.settings`;
never the HTTP layer or the CLI.
"""
