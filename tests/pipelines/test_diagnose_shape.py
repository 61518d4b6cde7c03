"""The template fit of pipelines.diagnose_shape measures what it says: fitted to the GT normals it comes closer to
them than the sphere it starts from."""
from pipelines import diagnose_shape


def test_the_template_fitted_to_the_gt_normals_comes_closer_than_the_sphere(tiny_glossy):
    start = diagnose_shape.diagnose(str(tiny_glossy), objects=1, steps=1, signals=("normals",))
    fitted = diagnose_shape.diagnose(str(tiny_glossy), objects=1, steps=80, signals=("normals", "silhouettes"))
    assert [row[0] for row in fitted] == ["normals", "silhouettes"]
    sphere, normals = float(start[0][1]), float(fitted[0][1])
    assert normals < 0.7 * sphere, (sphere, normals)
