"""HTTP: the FastAPI app (:mod:`.app`), thin routes, problems (errors), dependencies,
submission, results, metrics, OpenAPI; and the pages for people (:mod:`.pages`: home, 3-D
viewer, report) with the viewer's frames (:mod:`.frames`).

`service.api.app.create_app` assembles them; routes stay thin and call the modules here.
"""
