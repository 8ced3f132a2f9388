// Operator schemas of the `diffavatar` namespace and the Python module `torch_diffavatar._C`.
//
// Importing `torch_diffavatar._C` loads this shared library, whose static initialisers register the
// schemas below (TORCH_LIBRARY) and the CPU kernels of the other files (TORCH_LIBRARY_IMPL). The
// Python module itself is empty. The contract of every op (shapes, units, maths) is documented in
// torch_diffavatar/sim/reference.py, which holds the PyTorch twin of each kernel.

#include <Python.h>
#include <torch/library.h>

extern "C" {
// An empty module: `import torch_diffavatar._C` only has to load the library (pattern of PyTorch's
// cpp_custom_ops tutorial, without pybind11).
PyObject* PyInit__C(void) {
  static struct PyModuleDef module_def = {
      PyModuleDef_HEAD_INIT,
      "_C",  // name
      "C++ kernels of torch_diffavatar, registered as torch.ops.diffavatar.*",
      -1,  // per-interpreter state size
      nullptr,  // methods
  };
  return PyModule_Create(&module_def);
}
}

TORCH_LIBRARY(diffavatar, m) {
  // Colour-ordered Gauss-Seidel pass of the orthotropic StVK stretch constraints (one 3-vector block
  // per triangle), in place on x and lam.
  m.def(
      "stretch_project_(Tensor(a!) x, Tensor(b!) lam, Tensor vert_inv_mass, Tensor tri_vertices, "
      "Tensor tri_rest_inv, Tensor tri_compliance, Tensor order, Tensor color_offsets, float dt) -> ()");
  // Jacobi pass of the same constraints: all corrections from the same x, averaged per vertex.
  m.def(
      "stretch_project_jacobi_(Tensor(a!) x, Tensor(b!) lam, Tensor vert_inv_mass, Tensor tri_vertices, "
      "Tensor tri_rest_inv, Tensor tri_compliance, float dt, float omega) -> ()");
  // Colour-ordered Gauss-Seidel pass of the signed dihedral-angle bending constraints.
  m.def(
      "bend_project_(Tensor(a!) x, Tensor(b!) lam, Tensor vert_inv_mass, Tensor edge_quads, "
      "Tensor edge_rest_angle, Tensor edge_compliance, Tensor order, Tensor color_offsets, float dt) -> ()");
  // Jacobi pass of the bending constraints.
  m.def(
      "bend_project_jacobi_(Tensor(a!) x, Tensor(b!) lam, Tensor vert_inv_mass, Tensor edge_quads, "
      "Tensor edge_rest_angle, Tensor edge_compliance, float dt, float omega) -> ()");
  // Fused XPBD substeps (predict, iterations x (stretch, bend, attachments, body contacts, stitches),
  // friction, velocity update), in place on x and v; twin: reference.xpbd_substeps_. The arguments are
  // grouped by role; sim/substep.py (SubstepInputs) builds them and documents each list's layout:
  //   stretch = [tri_vertices, tri_rest_inv, tri_compliance, tri_order, tri_color_offsets]
  //   bend = [edge_quads, edge_rest_angle, edge_compliance, edge_order, edge_color_offsets]
  //   seams = [stitch_vertices, attach_vertices, attach_height]
  //   body = [body_verts, body_faces, contact_vert, contact_tri, contact_bary]
  //   coefficients = [gravity x, y, z, velocity_decay, dt, stitch_compliance, stitch_max_move,
  //                   stitch_snap, attach_compliance, thickness, friction, jacobi_omega, contact_bounce]
  m.def(
      "xpbd_substeps_(Tensor(a!) x, Tensor(b!) v, Tensor vert_inv_mass, Tensor[] stretch, Tensor[] bend, "
      "Tensor[] seams, Tensor[] body, float[] coefficients, int substeps, int iterations, bool jacobi, "
      "int num_threads) -> ()");
  // Largest |Green strain component| over the triangles (0-dim tensor): the solver's blow-up test.
  m.def("max_abs_green_strain(Tensor x, Tensor tri_vertices, Tensor tri_rest_inv) -> Tensor");
  // Closest point on a triangle mesh within max_dist (uniform grid + exact point-triangle distance).
  m.def(
      "closest_point_on_mesh(Tensor points, Tensor verts, Tensor faces, float max_dist) "
      "-> (Tensor tri, Tensor bary, Tensor dist)");
}
