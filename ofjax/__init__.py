"""ofjax: OpticFusion in JAX.

Fuses white-light-interferometry (WLI) height maps and optical-microscope (OM) photos of a
microstructure into one neural SDF, and exports a coloured, metrically exact mesh in micrometres.
"""

__version__ = "0.1.0"
