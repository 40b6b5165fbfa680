"""Local geometry of point clouds by PCA of neighbourhoods (the registration study, step 4; notebook 04).

For every point the neighbourhood (k nearest neighbours or a ball,
:mod:`labkit.neighbours`) is reduced to its centroid and summarised by its 3x3
covariance; the sorted eigen decomposition gives the normal, the local noise and the
eigenvalue features used to select and weight correspondences. Notation (notebook 04):

- (eq. 1) centroid            p_bar = 1/m sum_j p_j
- (eq. 2) covariance          C = 1/m sum_j (p_j - p_bar)(p_j - p_bar)^T
- (eq. 3) eigen decomposition C = V diag(l1, l2, l3) V^T with l1 >= l2 >= l3 >= 0
- (eq. 4) normal              n = v3 (eigenvector of the smallest eigenvalue)
- (eq. 5) local noise         sigma_n = sqrt(m l3 / (m - 3))
- (eq. 6-8) eigenvalue features on e_i = l_i / (l1 + l2 + l3)
- (eq. 9) plane through three points n = (p2 - p1) x (p3 - p1) (robust normals)

One module per concept:

- :mod:`~labkit.features.pca`: :func:`local_pca`, :func:`normals`, :func:`local_noise` (eqs. 1-5);
  :func:`pca_at` at chosen points of a kd-tree one already has
- :mod:`~labkit.features.eigen`: :func:`eigen_features` (eqs. 6-8)
- :mod:`~labkit.features.multiscale`: :func:`multiscale_features` (least eigenentropy)
- :mod:`~labkit.features.robust`: :func:`robust_normals` (RANSAC / LMedS planes, eq. 9)

The registration study warns that ``np.linalg.eig`` does not sort its eigenvalues; the PCA uses an
eigh (``labkit.neighbours.eigh3.eigh3``, the decomposition of ``np.linalg.eigh`` compiled for
stacks of 3x3 matrices) and reverses the order once, in ``sorted_eigh``.
"""

from ..neighbours.moments import covariances
from ..neighbours.search import CHUNK_SIZE, LEAFSIZE, Neighbourhoods, neighbourhoods
from ._steps import DUPLICATES, ORIENTATIONS, sorted_eigh
from .eigen import EigenFeatures, eigen_features
from .multiscale import MultiScaleFeatures, multiscale_features
from .pca import LocalPCA, local_noise, local_pca, normals, pca_at
from .robust import RobustNormals, robust_normals

__all__ = [
    "CHUNK_SIZE", "DUPLICATES", "LEAFSIZE", "ORIENTATIONS", "EigenFeatures", "LocalPCA", "MultiScaleFeatures",
    "Neighbourhoods", "RobustNormals", "eigen_features", "local_noise", "local_pca", "multiscale_features",
    "neighbourhoods", "normals", "pca_at", "robust_normals",
]  # fmt: skip
