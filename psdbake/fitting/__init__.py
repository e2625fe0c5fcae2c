"""From sculpts to correctives groups: examples gathered and checked, regions planned, each group's
RBF fitted over its examples' poses, combinations on top, the product checked through a client.

``examples``    the EXAMPLES files' sculpts, every one checked before any is solved
``regions``     which examples drive which group: local, additive groups by default
``drivers``     a group's driver joints, RBF centres and fit
``rbf_fit``     the cardinal RBF fitted with SciPy's RBFInterpolator, its system checked first
``correctives`` one mesh's groups fitted, combinations made to carry what their joints' do not
``groups``      groups in one CORRECTIVES layer: read, merged, checked, authored
``fitcheck``    the product at every example through the composition a client uses
"""
