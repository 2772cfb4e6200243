"""The synthetic driving world (``odg synth``): procedural city scenes rendered by ray casting
into a nuScenes-format dataroot with Occ3D-style ground truth. Start at generate.py."""
