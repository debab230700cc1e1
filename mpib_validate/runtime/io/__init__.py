"""Files: OpenEXR reading and writing, atomic outputs, previews, the camera header."""
