"""Training-free registration: lift per-mask embeddings onto Gaussians (Dr. Splat, Sec. 3).

For every training view the rasterizer keeps, per pixel, the top-k Gaussians by blending weight
w = T·α. Pixel p lies in mask j of that view (LangSplat feature files, one level), so Gaussian i
collects w_ij = Σ_{p ∈ mask j} w_i(p). Each Gaussian's feature is

    f_i = normalize(Σ_j w_ij f_j / Σ_j w_ij) = normalize(Σ_j w_ij f_j)

and its weight W_i = Σ_j w_ij (0 = never seen inside a mask: unassigned, pruned). No N x M matrix
(Gaussians x masks) is ever formed: views are coalesced into sparse (Gaussian, mask) pairs and
summed per Gaussian block.

The flow, one module per stage (docs/ARCHITECTURE.md draws it):

    options     RegisterOptions, checked up front
    views       cameras paired with feature files
    plan        one block of Gaussians, or blocks that fit --memory-budget
    compute     one view: rasterize (engine) -> aggregation hook -> coalesce   (coalesce.py)
    executor    where views are computed: local | ray (ray.py)
    aggregate   the --aggregate modes: per-view hooks, per-Gaussian statistics, a step on the sums
    checkpoint  the pair log (pairlog.py) and the mode's statistics: resume
    sink        per-block sums (sums.py): live in memory, or replayed from the log
    output      targets: the registered PLY (one writer), or arrays in memory
    driver      the one driver: register (to a PLY), register_features (in memory)
"""

from drsplat.registration.driver import RegistrationResult, register, register_features
from drsplat.registration.options import RegisterOptions

__all__ = ["RegisterOptions", "RegistrationResult", "register", "register_features"]
