import numpy as np

import minidiff as md


def test_square_sum_gradient():
    x = md.tensor([1.0, -2.0, 3.0], requires_grad=True)
    (x * x).sum().backward()
    np.testing.assert_allclose(x.grad, [2.0, -4.0, 6.0])
