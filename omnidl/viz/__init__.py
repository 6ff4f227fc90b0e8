"""omnidl.viz"""
