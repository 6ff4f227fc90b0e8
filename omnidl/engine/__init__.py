"""omnidl.engine"""
