"""LightningModules for the two stages, and the callbacks they share."""

from nerfart_plugin.systems.reconstruction import ReconstructionSystem
from nerfart_plugin.systems.stylization import StylizationSystem

__all__ = ["ReconstructionSystem", "StylizationSystem"]
