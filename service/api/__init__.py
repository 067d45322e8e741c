"""The REST API: problems (errors), dependencies, submission, results, metrics, OpenAPI, routes.

`service.app.create_app` assembles them; routes stay thin and call the modules here.
"""
