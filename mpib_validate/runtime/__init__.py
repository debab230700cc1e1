"""The refocus runtime: what the Blender extension ships and the ``mpib refocus`` command runs.

Camera and lens, image I/O (EXR, photographs, camera headers), MPI layers (passes, photo
refinement, hidden-background fill, layered renders), the compositor (kernels, Eq. 1, the
sub-aperture middle setting) and the refocus pipeline with its session, disk cache and
memory budget. It imports nothing of the validation harness (card scenes, tracer,
references, metrics, benches); ``tests/test_import_graph.py`` checks that.
"""
