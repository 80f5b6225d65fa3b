"""companion: visual positioning for indoor, GPS-denied drones."""

__version__ = "0.1.0"
