"""omnidl.utils"""
