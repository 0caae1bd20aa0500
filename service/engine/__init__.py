"""The chain behind the routes: the model's steps, completions and meshes (``pipeline``), and grasp
planning in a pool of worker processes (``planning``)."""
