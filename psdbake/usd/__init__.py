"""The only package that imports pxr: reading stages, the UsdSkel black box, writing layers."""
