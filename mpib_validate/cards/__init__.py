"""The card world: the scene model of the paper's generator, its textures, the Eq. 15 ray tracer
with its aperture and pixel samples, the dataset runner, and the scoring of card renders."""
