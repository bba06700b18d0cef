"""lasagna.compose"""
