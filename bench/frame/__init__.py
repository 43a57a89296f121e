"""How fast and how exact one frame is: the splatter and the deformation, per backend, precision and size."""
