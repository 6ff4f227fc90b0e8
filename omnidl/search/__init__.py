"""omnidl.search"""
