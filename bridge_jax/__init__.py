"""bridge_jax: unsupervised stereo matching and optical flow from stereo video in JAX/Flax.

Reimplements "Bridging Stereo Matching and Optical Flow via Spatiotemporal Correspondence"
(Lai, Tsai, Chiu, CVPR 2019): one network P(Ia, Ib) gives a 2-channel correspondence map at 4 scales;
applied to the 4 image pairs of a stereo-video cycle it yields disparity and optical flow.
"""

__version__ = "0.1.0"
