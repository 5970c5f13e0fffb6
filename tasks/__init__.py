"""Not code: makes this folder the import package `lightplan_tasks` (pyproject.toml maps the name
onto tasks/), so the example tasks are installed with the distribution and `cell bench` finds its
defaults with importlib.resources, in a regular install as in an editable one."""
