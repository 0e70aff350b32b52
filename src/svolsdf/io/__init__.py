"""svolsdf.io"""
