"""From the bundled CT head to a shape model and predicted landmarks, step by step.

The same steps as `o3dreg demo`, written out as the tutorial does.

    python examples/ct_to_model.py [OUTPUT_FOLDER]
"""

import sys
import tempfile

import numpy as np

import o3dreg
from o3dreg.app.datasets import headsq_path
from o3dreg.app.demo import make_population

output = sys.argv[1] if len(sys.argv) > 1 else tempfile.mkdtemp(prefix="o3dreg-")

# 1. CT volume -> bone surface in millimetres.
volume = o3dreg.read_volume(headsq_path())
bone = o3dreg.isosurface(volume, 1150.0)  # raw units; HU = raw - 1024
bone = o3dreg.smooth_taubin(o3dreg.keep_largest_components(bone), 10)
print(volume, "->", len(bone.vertices), "vertices")

# 2. The low-density template.
template = o3dreg.decimate(bone, 2500)

# 3. A population with known ground truth (smooth warps, rigid motions, remeshing).
patients = make_population(bone, 6, seed=1)

# 4. Batch registration: one semilandmark mesh per patient, saved as each finishes.
batch = o3dreg.register_batch(
    template, [p.mesh for p in patients], output, names=[p.name for p in patients]
)
print(batch.table())

# 5. Procrustes + PCA: P = M + A alpha, of the patients whose verdict is 'ok' only.
names, shapes = batch.shapes(accepted_only=True)
model = o3dreg.build_shape_model(shapes, np.asarray(template.triangles), names=names)
print(model.variance_table())

# 6. A landmark on the template, carried to a new patient by fitting the model.
new = make_population(bone, 1, seed=99)[0]
tip = int(np.argmax(np.asarray(template.vertices)[:, 2]))
landmarks = o3dreg.TemplateLandmarks.from_vertices(template, [tip], labels=["vertex"])
prediction = o3dreg.predict_landmarks(model, landmarks, new.mesh)
truth = new.truth(landmarks.positions(np.asarray(template.vertices)))
print("predicted", prediction.positions[0].round(1), "truth", truth[0].round(1))
error = o3dreg.landmark_errors(prediction.positions, truth)[0]
print(f"error {error:.2f} mm (verdict {prediction.status}); results in {output}")
