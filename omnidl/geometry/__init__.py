"""omnidl.geometry"""
