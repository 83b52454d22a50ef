"""Looking at maps: a browser viewer (viser), held-out comparison pictures, fly-through videos.

Nothing here is imported by ``import eligsir_o3d``; viser is needed only by the viewer (``[view]`` extra).
"""
