"""svolsdf.optimize"""
